"""Firmware benchmark: wall time of a GC/GO cycle, RealTime cycles per second in-process, and
simulated seconds per wall second while looping.

Run: /work/venv/bin/python benchmarks/bench_firmware.py [--cycles N]
"""
from __future__ import annotations

import argparse
import time

from bh8_gym.firmware import Firmware


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=2000, help="RealTime cycles per baud rate (default: %(default)s)")
    args = parser.parse_args()

    fw = Firmware(store_dir=None, seed=0)
    fw.transact(b"HI\r")

    start_wall, start_sim = time.perf_counter(), fw.time
    fw.transact(b"GC\r")
    fw.transact(b"GO\r")
    wall, sim = time.perf_counter() - start_wall, fw.time - start_sim
    print(f"GC+GO: {wall * 1000:.0f} ms wall for {sim:.3f} s simulated ({sim / wall:.1f}x real time)")

    for baud in (96, 384):
        fw.transact(b"PSET BAUD %d\r" % baud)
        fw.transact(b"LOOP\r")
        layout = fw.loop_layout
        blocks = [layout.encode_control([v, 60] * 4) for v in (20, -20)]
        start_wall, start_sim = time.perf_counter(), fw.time
        for k in range(args.cycles):
            fw.write(blocks[(k // 50) % 2])
            fw.run_until_idle()
            fw.read()
        wall, sim = time.perf_counter() - start_wall, fw.time - start_sim
        fw.transact(b"\x03")
        print(
            f"RealTime at {baud * 100} baud (default flags, 4 motors): {args.cycles / wall:.0f} cycles/s wall, "
            f"{sim / args.cycles * 1000:.2f} ms simulated per cycle, {sim / wall:.1f} simulated s per wall s"
        )

    snap = fw.snapshot()
    start_wall = time.perf_counter()
    for _ in range(200):
        fw.restore(snap)
    print(f"snapshot restore: {(time.perf_counter() - start_wall) / 200 * 1e6:.0f} µs")
    fw.shutdown()


if __name__ == "__main__":
    main()
