"""Builds bh8-gym (the metadata is in pyproject.toml) and compiles the per-step modules with Cython.

Cython compiles these Python sources as they are (annotations are not taken as C types, so every
call keeps Python's semantics and results): our work per physics step takes about 12 µs instead of
17, with bit-identical trajectories (benchmarks/bench_envs.py, tests/test_compilation.py). A build
without a C compiler, or without Cython (pip's --no-build-isolation), skips them, and the package
runs from its sources.
"""
from setuptools import Extension, setup

try:
    from Cython.Build import cythonize
except ImportError:
    cythonize = None

# The modules a simulated physics step or RealTime cycle runs through.
COMPILED_MODULES = (
    "bh8_gym.plant",
    "bh8_gym.motion_control",
    "bh8_gym.firmware",
    "bh8_gym.realtime_codec",
    "bh8_gym.envs.base",
    "bh8_gym.envs.grasp",
    "bh8_gym.envs.finger_reach",
    "bh8_gym.envs.scenes",
)

setup(
    ext_modules=[] if cythonize is None else cythonize(
        [
            Extension(
                name, [name.replace(".", "/") + ".py"], optional=True,
                # No fused multiply-add: floats must round exactly as in the interpreter.
                extra_compile_args=["-ffp-contract=off"],
            )
            for name in COMPILED_MODULES
        ],
        build_dir="build/cython",
        compiler_directives={"language_level": 3, "annotation_typing": False},
        quiet=True,
    ),
)
