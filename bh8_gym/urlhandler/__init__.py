"""pyserial URL handlers of bh8-gym: `bh8sim://`, the simulated hand in this process.

pyserial finds a handler for `scheme://...` as module `protocol_<scheme>` in the packages listed
in `serial.protocol_handler_packages`. Importing this package appends "bh8_gym.urlhandler" to that
list (once), after which

    import serial, bh8_gym.urlhandler
    port = serial.serial_for_url("bh8sim://?seed=0&firmware=4.3&state=/tmp/hand", timeout=1)

gives a pyserial port object talking to an in-process `Firmware` (see `protocol_bh8sim`). This
is how tests, notebooks and Windows users without pseudo-terminals reach the simulator.
"""
import serial

HANDLER_PACKAGE = "bh8_gym.urlhandler"

if HANDLER_PACKAGE not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(HANDLER_PACKAGE)
