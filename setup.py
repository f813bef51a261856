"""Builds bh8-gym (the metadata is in pyproject.toml) and compiles the per-step modules with Cython.

Cython compiles these Python sources as they are (annotations are not taken as C types, so every
call keeps Python's semantics and results): our work per physics step takes about 12 µs instead of
17, with bit-identical trajectories (benchmarks/bench_envs.py, tests/test_compilation.py). A build
without a C compiler, or without Cython (pip's --no-build-isolation), skips them, and the package
runs from its sources.
"""
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

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


class BuildOrSkip(build_ext):
    """Skips a module that does not compile (no C compiler): it then runs from its source. (An
    Extension's `optional` flag misses the error some setuptools versions raise for a failed
    compiler, and an editable install would then look for the missing file.)"""

    def build_extensions(self):
        self.check_extensions_list(self.extensions)
        built = []
        for ext in self.extensions:
            try:
                self.build_extension(ext)
            except Exception as error:
                print(f"bh8-gym: {ext.name} not compiled, it runs from source ({error})", file=sys.stderr)
            else:
                built.append(ext)
        self.extensions = built


setup(
    cmdclass={"build_ext": BuildOrSkip},
    ext_modules=[] if cythonize is None else cythonize(
        [
            Extension(
                name, [name.replace(".", "/") + ".py"],
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
