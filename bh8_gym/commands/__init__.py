"""The `bh8` subcommands that are not agents: `serve`, `term`, `render`, `calibrate` (bh8_gym.cli dispatches).

Each module provides `configure_parser(parser)` and `run(args) -> int`; the library modules they
drive (serial_server, terminal, rendering, simulator) carry no command-line code.
"""
