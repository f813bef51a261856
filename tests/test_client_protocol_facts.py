"""Protocol facts the manual is silent on and public clients rely on (SPEC.md §2, docs/clients.md).

Run through the `link` fixture (in-process and through the pty of `bh8 serve`).
"""
PROMPT = b"=> "


def test_reset_drops_an_unsaved_baud_and_keeps_a_saved_one(link):
    """SPEC.md §2 RESET: parameters come back from non-volatile storage, so a PSET BAUD not saved
    with PSAVE is gone. Barrett's C++ API 4.4.3 relies on it: it sends a bare CR, then RESET, and
    reads the reply at 9600 ("Baud rate can be saved between resets by executing the PSAVE
    command")."""
    assert link.lines("PSET BAUD 384") == []
    link.write(b"\r")
    assert link.read_until(PROMPT, 10) == b"\n\r=> "
    assert b"BarrettHand Firmware\n" in link.command("RESET")
    assert link.lines("PGET BAUD") == ["96"]

    assert link.lines("PSET BAUD 192") == []
    assert link.lines("PSAVE") == []
    assert b"BarrettHand Firmware\n" in link.command("RESET")
    assert link.lines("PGET BAUD") == ["192"]
