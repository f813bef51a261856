"""A small sample of benchmarks/fuzz_files.py (issue 39's fuzz of every file format bh8-gym reads):
a few generated hostile files of each format, read as the package reads them in a limited worker
process. None may crash the worker, hang, run away with memory, run a payload or raise anything but
a refusal (a ValueError or TrainingError naming the file). The script runs thousands per format;
docs/benchmarks.md has its figures.
"""
from __future__ import annotations

import importlib.util
import os
import random
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "fuzz_files.py"


@pytest.fixture(scope="module")
def fuzz(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("fuzz_files", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "markers").mkdir()
    (folder / "big.png").write_bytes(module.big_png(64, 64))  # the script's is 12000 x 12000: never opened either
    return module, folder, module.seeds(folder)


@pytest.mark.timeout(600)
@settings(max_examples=1, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1))
def test_hostile_files_of_every_format_are_read_or_refused(fuzz, seed):
    module, folder, base = fuzz
    rng = random.Random(seed)
    paths = [(fmt, path) for fmt in module.FORMATS for path in generate(module, fmt, folder, rng, base, seed)]
    verdicts = module.run(paths, folder, timeout=60.0, memory_mb=1024)
    bad = [(Path(path).name, verdict) for (_, path), verdict in zip(paths, verdicts)
           if not verdict.startswith(("accepted", "refused"))]
    assert not bad, bad
    assert not os.listdir(folder / "markers")  # no payload ran


def generate(module, fmt, folder, rng, base, seed):
    sample = folder / f"{fmt}-{seed}"
    sample.mkdir()
    for name in ("good.obj", "badface.obj", "trunc.hdr", "big.png"):
        os.symlink(folder / name, sample / name)
    (sample / "markers").symlink_to(folder / "markers")
    return module.generate(fmt, 2, sample, rng, base)
