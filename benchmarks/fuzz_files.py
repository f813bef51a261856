"""Fuzz every kind of file bh8-gym reads: generated hostile OBJ, MTL, STL, URDF, .npz, .zip, TOML and
JSON files, each read the way the package reads it, in worker processes under a time and a memory
limit, and counted: accepted, refused (a ValueError or TrainingError naming the file), crashes (the
worker killed by a signal), hangs (past --timeout), runaways (MemoryError, or the worker's peak
memory grown by more than --memory-mb), payloads run (a pickle that makes a marker folder), and
other exceptions (what would have been a raw traceback without bh8's last line of defence).

Each file starts from a valid one (a mesh, an export, an SB3 model, a shipped config, a run's
records) and is mutated: hostile numbers (1e308, NaN, -1, 2**64, strings), types swapped, keys
dropped or added, lines and bytes cut, repeated or inserted, deep nesting, compressed or encrypted
zip members, .npy headers that declare more than they hold, pickles with a payload, and for
meshes the issue's references (an MTL naming a long texture, a truncated HDR, a 12000 x 12000 PNG).
A mesh or URDF that is accepted is loaded into PyBullet and rendered (the renderer decodes
textures), an export or SB3 model is run on a test observation, a config is checked, a record is
read with its schema.

Run: python benchmarks/fuzz_files.py [--files 2000] [--formats obj mtl ...] [--seed 0]
"""
from __future__ import annotations

import argparse
import base64
import io
import json
import os
import random
import re
import resource
import select
import signal
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
import zlib
from pathlib import Path

FORMATS = ("obj", "mtl", "stl", "urdf", "npz", "zip", "toml", "json")
HOSTILE_NUMBERS = ["1e308", "-1e308", "nan", "inf", "-1", "0", "1e39", "18446744073709551616", "1e-320", "-0",
                   "0x10", "1_0", '"x"', "true", "[]", "{}", "3.5", "99999999999"]
HOSTILE_LINES = ["mtllib evil.mtl", "usemtl " + "m" * 5000, "f 1 2 999999", "f 0 1 2", "f -9 -8 -7", "v nan 0 0",
                 "v 1e39 0 0", "g", "o " + "x" * 3000, "f 1/0/0 2 3", "\0", "x" * 100_000, "vt 0 0", "s off",
                 "f " + " ".join(str(i) for i in range(1, 400))]
IGNORED_LINES = ["mtllib evil.mtl", "mtllib " + "A" * 2000 + ".mtl", "usemtl " + "m" * 5000, "o " + "x" * 3000,
                 "g", "vt 0 0", "vn 0 0 1", "s off", "# " + "c" * 100_000, "l 1 2", "f 1 2", "vp 0 0 0"]
TETRA = "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


# -- generation ----------------------------------------------------------------------------------


def mutate_text(text: str, rng: random.Random, lines: list[str]) -> str:
    """A text with 1-4 of: a number made hostile, a line removed, repeated or inserted, a cut."""
    parts = text.split("\n")
    for _ in range(rng.randint(1, 4)):
        choice = rng.random()
        if choice < 0.35 and parts:
            i = rng.randrange(len(parts))
            tokens = parts[i].split(" ")
            j = rng.randrange(len(tokens))
            tokens[j] = rng.choice(HOSTILE_NUMBERS)
            parts[i] = " ".join(tokens)
        elif choice < 0.5 and parts:
            del parts[rng.randrange(len(parts))]
        elif choice < 0.65 and parts:
            i = rng.randrange(len(parts))
            parts[i:i] = [parts[i]] * rng.choice([2, 10, 1000])
        elif choice < 0.85:
            parts.insert(rng.randint(0, len(parts)), rng.choice(lines))
        else:
            cut = "\n".join(parts)
            return cut[:rng.randint(0, len(cut))]
    return "\n".join(parts)


def mutate_numbers(text: str, rng: random.Random) -> str:
    """`text` with 1-3 of its decimal numbers (inside attribute values) replaced by hostile ones."""
    numbers = list(re.finditer(r"(?<=[\" ])-?[0-9][0-9.e-]*(?=[\" ])", text))
    for found in sorted(rng.sample(numbers, min(len(numbers), rng.randint(1, 3))), key=lambda m: -m.start()):
        replacement = rng.choice(["1e308", "-1", "0", "nan", "inf", "1e-300", "2e9", "x", "", "1 2", "0.5"])
        text = text[:found.start()] + replacement + text[found.end():]
    return text


def mutate_value(value, rng: random.Random, marker: str):
    """A JSON value with one leaf (or the whole) replaced by a hostile one."""
    hostile = [1e308, -1e308, -1, 0, 2**64, 10**30, "x", "", True, None, [], {}, [1] * 5, {"a": {"b": 1}},
               "1e308", float("nan"), float("inf"), {"py/object": "os.system"}, [[[[[[[[[]]]]]]]]],
               {":serialized:": base64.b64encode(payload(marker)).decode(), ":type:": "<class 'x'>"}]
    if isinstance(value, dict) and value and rng.random() < 0.8:
        key = rng.choice(sorted(value))
        value = dict(value)
        if rng.random() < 0.15:
            del value[key]
        else:
            value[key] = mutate_value(value[key], rng, marker)
        if rng.random() < 0.1:
            value["unexpected_" + str(rng.randint(0, 9))] = rng.choice(hostile)
        return value
    if isinstance(value, list) and value and rng.random() < 0.7:
        value = list(value)
        i = rng.randrange(len(value))
        value[i] = mutate_value(value[i], rng, marker)
        return value
    return rng.choice(hostile)


def payload(marker: str) -> bytes:
    """A pickle whose loading makes the folder `marker` (proof that it ran)."""
    return b"cos\nmkdir\n(V" + marker.encode() + b"\ntR."


def mutate_zip(data: bytes, rng: random.Random, marker: str) -> bytes:
    """A zip with one member rewritten, recompressed under another method, or its bytes damaged."""
    choice = rng.random()
    if choice < 0.55:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            members = {info.filename: (info, archive.read(info.filename)) for info in archive.infolist()}
        name = rng.choice(sorted(members))
        info, content = members[name]
        if name in ("data", "metadata.npy") or name.endswith(".json"):
            try:
                content = json.dumps(mutate_value(json.loads(content), rng, marker)).encode()
            except ValueError:
                content = content[:len(content) // 2]
        elif name.endswith(".npy"):
            content = mutate_npy(content, rng)
        else:
            content = rng.choice([content[:len(content) // 2], payload(marker), content * 3, b"\0" * 64])
        if rng.random() < 0.1:
            members["extra.pkl"] = (zipfile.ZipInfo("extra.pkl"), payload(marker))
        out = io.BytesIO()
        method = rng.choice([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
        with zipfile.ZipFile(out, "w", compression=method) as archive:
            for key, (_, value) in members.items():
                archive.writestr(key if key != name else name, content if key == name else value)
        return out.getvalue()
    raw = bytearray(data)
    if choice < 0.75:  # flip bytes
        for _ in range(rng.randint(1, 20)):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
    elif choice < 0.85:  # a method number no reader has, or sizes that lie
        at = raw.find(b"PK\x03\x04")
        if at >= 0:
            raw[at + 8:at + 10] = struct.pack("<H", rng.choice([1, 6, 9, 14, 98, 99]))
            raw[at + 22:at + 26] = struct.pack("<I", rng.choice([0, 2**31, 2**32 - 1]))
    else:
        raw = raw[:rng.randint(0, len(raw))]
    return bytes(raw)


def mutate_npy(content: bytes, rng: random.Random) -> bytes:
    """An .npy whose header declares another dtype or a shape it does not hold."""
    descr = rng.choice(["<f8", "<f4", "|i1", "<i8", "<U100000", "|O", "<c16", ">f8", "|b1"])
    shape = rng.choice([(10**11,), (0,), (3, 3), (2**31, 2**31), (-1,), (), (1,) * 40])
    header = io.BytesIO()
    try:
        import numpy as np

        np.lib.format.write_array_header_1_0(header, {"descr": descr, "fortran_order": False, "shape": shape})
    except (ValueError, TypeError):
        return content[:len(content) // 2]
    return header.getvalue() + content[128:][:rng.choice([0, 64, 4096])]


def seeds(folder: Path) -> dict[str, object]:
    """The valid files each format's mutations start from."""
    import numpy as np
    import pybullet_data

    root = Path(pybullet_data.getDataPath()) / "random_urdfs"
    objs = [TETRA, *((root / f"{n:03d}" / f"{n:03d}.obj").read_text() for n in (0, 105, 333))]
    urdf = ('<robot name="r"><link name="base"><contact><lateral_friction value="1"/></contact><inertial>'
            '<origin xyz="0 0 0"/><mass value="0.1"/><inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" '
            'izz="1e-4"/></inertial><visual><geometry><mesh filename="good.obj" scale="1 1 1"/></geometry>'
            '<material name="m"><color rgba="1 0 0 1"/></material></visual><collision><geometry>'
            '<mesh filename="good.obj"/></geometry></collision></link><link name="tip"><collision><geometry>'
            '<box size="0.01 0.02 0.03"/></geometry></collision></link><joint name="j" type="revolute">'
            '<parent link="base"/><child link="tip"/><origin xyz="0 0 0.05" rpy="0 0 0"/><axis xyz="0 0 1"/>'
            '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    (folder / "good.obj").write_text(TETRA)
    (folder / "badface.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n")
    (folder / "trunc.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 16\n\x02\x02\x00\x10")
    weights = {"layer0_weight": np.zeros((16, 15)), "layer0_bias": np.zeros(16), "layer1_weight": np.zeros((4, 16)),
               "layer1_bias": np.zeros(4)}
    npz = io.BytesIO()
    np.savez(npz, format=np.array("bh8-numpy-policy/1"), metadata=np.array(json.dumps(
        {"algorithm": "PPO", "activation": "tanh", "n_layers": 2, "output_transform": "clip",
         "env_id": "BH8FingerReach-v0", "env_kwargs": {}})), obs_mean=np.zeros(15), obs_var=np.ones(15),
        obs_epsilon=np.array(1e-8), obs_clip=np.array(10.0), action_low=-np.ones(4) * 127,
        action_high=np.ones(4) * 127, **weights)
    configs = sorted((Path(__file__).resolve().parents[1] / "agents" / "configs").glob("*.toml"))
    return {"obj": objs, "urdf": urdf, "npz": npz.getvalue(), "zip": _sb3_model(),
            "toml": [path.read_text() for path in configs], "json": _records()}


def _sb3_model() -> bytes:
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env

    env = make_env("BH8FingerReach-v0", {})
    try:
        model = PPO("MlpPolicy", env, seed=0, device="cpu", n_steps=64, batch_size=64, policy_kwargs={"net_arch": [16]})
    finally:
        env.close()
    out = io.BytesIO()
    model.save(out)
    return out.getvalue()


def _records() -> dict[str, dict]:
    return {
        "latest.json": {"num_timesteps": 4096, "total_timesteps": 8192, "next_evaluation": 5120,
                        "best_success_rate": 0.5, "best_mean_return": 3.0, "best_timesteps": 4096},
        "trial.json": {"trial_id": "t0000", "seed": 0, "space": {}, "attempts": 1, "wall_seconds": 3.0,
                       "starts": [0]},
        "result.json": {"metrics": {"best_validation_success": 0.5, "best_mean_return": 1.0}, "num_timesteps": 4096},
        "run.json": {"algorithm": "PPO", "env_id": "BH8FingerReach-v0", "env_kwargs": {}, "seed": 0},
    }


def generate(fmt: str, count: int, folder: Path, rng: random.Random, base: dict) -> list[str]:
    """`count` files of `fmt` in `folder` (each may come with companions: an OBJ's MTL, a texture)."""
    paths = []
    for index in range(count):
        marker = str(folder / "markers" / f"{fmt}{index}")
        name = folder / f"{fmt}{index:05d}"
        if fmt == "obj":
            path = name.with_suffix(".obj")
            # half with lines PyBullet's reader choked on but a mesh may carry (an MTL, long names)
            lines = HOSTILE_LINES if rng.random() < 0.5 else IGNORED_LINES
            path.write_text(mutate_text(rng.choice(base["obj"]), rng, lines), errors="replace")
        elif fmt == "mtl":
            path = name.with_suffix(".obj")
            texture = rng.choice(["A" * rng.choice([100, 1000, 5000]) + ".png", "trunc.hdr", "big.png", "/dev/zero",
                                  "../" * 50 + "etc/passwd", "%n%n%n.tga", "x.hdr"])
            mtl = mutate_text(f"newmtl m\nKd 1 0 0\nmap_Kd {texture}\nbump {texture}\n", rng,
                              ["map_Ka " + texture, "newmtl " + "n" * 4000, "Ns 1e308", "d nan"])
            name.with_suffix(".mtl").write_text(mtl, errors="replace")
            path.write_text(f"mtllib {name.with_suffix('.mtl').name}\nusemtl m\n" + TETRA)
        elif fmt == "stl":
            path = name.with_suffix(".stl")
            triangles = rng.randint(0, 6)
            spoiled = rng.random() < 0.5  # else every number a plain one
            body = b"".join(struct.pack("<12fH", *(rng.choice([float("nan"), float("inf"), 0.0]) if spoiled and
                                                   rng.random() < 0.1 else rng.uniform(-1, 1) for _ in range(12)), 0)
                            for _ in range(triangles))
            count_field = rng.choice([triangles, triangles, triangles + 1, 2**32 - 1, 0])
            data = b"\0" * 80 + struct.pack("<I", count_field) + body
            if rng.random() < 0.2:
                data = b"solid x\nfacet normal 0 0 1\nendsolid\n" if rng.random() < 0.5 else data[:rng.randint(0, 90)]
            path.write_bytes(data)
        elif fmt == "urdf":
            path = name.with_suffix(".urdf")
            lines = ['<deformable name="d"><visual filename="badface.obj"/></deformable>', "<!DOCTYPE r>",
                     '<mesh filename="badface.obj"/>', '<mesh filename="file:///dev/zero.obj"/>',
                     '<texture filename="trunc.hdr"/>', "<a>" * 500, '<joint name="k" type="floating"/>',
                     '<link name="base"/>', "&bogus;", '<mesh filename="x.dae"/>', "\0"]
            text = base["urdf"].replace("><", ">\n<")
            text = mutate_text(text, rng, lines) if rng.random() < 0.5 else mutate_numbers(text, rng)
            path.write_text(text, errors="replace")
        elif fmt in ("npz", "zip"):
            path = name.with_suffix("." + fmt)
            path.write_bytes(mutate_zip(base[fmt], rng, marker))
        elif fmt == "toml":
            path = name.with_suffix(".toml")
            path.write_text(mutate_text(rng.choice(base["toml"]), rng,
                                        ["[[x]]", "a.b.c.d.e.f.g = 1", "[env_kwargs.arm]\nhold_seconds = 1e300",
                                         'env_id = "CartPole-v1"', "[pretrain]\ndagger_iterations = 3",
                                         "x = " + "[" * 600 + "]" * 600, '"hyperparameters".batch_size = 1e9']))
        else:
            kind = rng.choice(sorted(base["json"]))
            path = folder / f"json{index:05d}-{kind}"
            path.write_text(json.dumps(mutate_value(base["json"][kind], rng, marker)) if rng.random() < 0.85
                            else rng.choice(["[" * 100_000, "{\"a\": NaN}", "", "\xff", "[1, 2]", "null"]),
                            errors="replace")
        paths.append(str(path))
    return paths


# -- reading, in a worker ------------------------------------------------------------------------


def read_one(fmt: str, path: str, client: int) -> str:
    """Read `path` as the package reads a file of `fmt`; "accepted" or "refused" (or raise)."""
    from bh8_gym.objects import ObjectLoader, ObjectSpec

    try:
        from bh8_gym.agents.training.trainer import TrainingError
    except ImportError:  # a checkout before agents/ was regrouped: meshes and URDFs only
        TrainingError = RuntimeError  # noqa: N806

    try:
        if fmt in ("obj", "mtl", "stl", "urdf"):
            import pybullet

            spec = (ObjectSpec("urdf", path=path, mass=None, friction=None) if fmt == "urdf"
                    else ObjectSpec("mesh", path=path, scale=1.0))
            body = ObjectLoader(client).create(spec, (0, 0, 0.1), (0, 0, 0, 1))
            pybullet.getCameraImage(16, 16, physicsClientId=client)
            pybullet.removeBody(body, physicsClientId=client)
        elif fmt in ("npz", "zip"):
            import numpy as np

            from bh8_gym.agents.deployment.policy_file import check_policy_runs, load_policy

            policy = load_policy(path)
            if hasattr(policy, "observation_dim"):
                check_policy_runs(policy, [np.zeros(policy.observation_dim, dtype=np.float32)], (policy.action_dim,))
        elif fmt == "toml":
            from bh8_gym.agents.training.config_check import check_rollout
            from bh8_gym.agents.training.train import load_config

            config = load_config(path)
            check_rollout(config, 2)
        else:
            from bh8_gym.agents.policy_io import check_metadata
            from bh8_gym.agents.sweep.trial import TRIAL_RECORD, TRIAL_RESULT
            from bh8_gym.agents.training.trainer import CHECKPOINT_STATE, read_run_json

            kind = path.rsplit("-", 1)[1]
            schema = {"latest.json": CHECKPOINT_STATE, "trial.json": TRIAL_RECORD, "result.json": TRIAL_RESULT}.get(kind)
            record = read_run_json(Path(path), schema)
            if kind == "run.json":
                check_metadata(record, path)
    except (ValueError, TrainingError):
        return "refused"
    return "accepted"


def worker(manifest: str, start: int, memory_mb: int, report: int) -> None:
    """Read the manifest's files from `start`, writing "start i" before and a verdict after each to
    the descriptor `report`."""
    import pybullet

    out = os.fdopen(report, "w", buffering=1)

    def say(line: str) -> None:
        out.write(line + "\n")
        out.flush()

    entries = [line.split("\t") for line in Path(manifest).read_text().splitlines()]
    client = pybullet.connect(pybullet.DIRECT)
    for index in range(start, len(entries)):
        fmt, path = entries[index]
        say(f"start {index}")
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        try:
            verdict = read_one(fmt, path, client)
        except MemoryError:
            verdict = "runaway MemoryError"
        except BaseException as error:  # noqa: BLE001 - what would have been a raw traceback
            verdict = f"uncaught {type(error).__name__}: {str(error)[:120]!r}"
        grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) >> 10
        if grown > memory_mb and not verdict.startswith("runaway"):
            verdict = f"runaway {grown} MB"
        say(f"done {index} {verdict}")


# -- the run -------------------------------------------------------------------------------------


def run(paths: list[tuple[str, str]], folder: Path, timeout: float, memory_mb: int) -> list[str]:
    """Each file's verdict, the workers restarted after a crash or a hang (which are counted)."""
    manifest = folder / "manifest.tsv"
    manifest.write_text("\n".join(f"{fmt}\t{path}" for fmt, path in paths))
    verdicts: list[str | None] = [None] * len(paths)
    start = 0
    limit = (memory_mb + 3072) << 20  # address space: the worker's own (torch, PyBullet) and the allowance

    def limits():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    while start < len(paths):
        # the verdicts on a pipe of their own: PyBullet prints to stdout from C, mid-line
        reader, writer = os.pipe()
        process = subprocess.Popen([sys.executable, __file__, "--worker", str(manifest), str(start), str(memory_mb),
                                    str(writer)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   preexec_fn=limits, start_new_session=True, pass_fds=(writer,))
        os.close(writer)
        current, began, buffer = None, time.monotonic(), b""
        while True:
            ready, _, _ = select.select([reader], [], [], 0.05)
            chunk = os.read(reader, 1 << 16) if ready else b""
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                word, index, *rest = line.decode(errors="replace").split(" ", 2)
                if word == "start":
                    current, began = int(index), time.monotonic()
                else:
                    verdicts[int(index)] = rest[0] if rest else "?"
                    current = None
            if ready and not chunk:  # end of the worker's output
                process.wait()
                break
            if current is not None and time.monotonic() - began > timeout:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
                verdicts[current] = "hang"
                break
        os.close(reader)
        if current is not None and verdicts[current] is None:
            code = process.returncode
            verdicts[current] = f"crash (signal {-code})" if code is not None and code < 0 else f"crash (exit {code})"
        done = [i for i, v in enumerate(verdicts) if v is not None]
        start = (max(done) + 1) if done else start + 1
    return [v or "?" for v in verdicts]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=2000, help="files per format (default: %(default)s)")
    parser.add_argument("--formats", nargs="+", choices=FORMATS, default=list(FORMATS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds per file before it is a hang")
    parser.add_argument("--memory-mb", type=int, default=1024, help="peak memory growth that is a runaway")
    parser.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker[0], int(args.worker[1]), int(args.worker[2]), int(args.worker[3]))
        return
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory(prefix="bh8-fuzz-") as temporary:
        folder = Path(temporary)
        (folder / "markers").mkdir()
        (folder / "big.png").write_bytes(big_png(12000, 12000))
        base = seeds(folder)
        print(f"{'format':6s} {'files':>6s} {'accepted':>9s} {'refused':>8s} {'crashes':>8s} {'hangs':>6s} "
              f"{'runaways':>9s} {'payloads':>9s} {'other exceptions':>17s} {'seconds':>8s}", flush=True)
        for fmt in args.formats:
            started = time.monotonic()
            paths = [(fmt, path) for path in generate(fmt, args.files, folder, rng, base)]
            verdicts = run(paths, folder, args.timeout, args.memory_mb)
            payloads = len([m for m in os.listdir(folder / "markers") if m.startswith(fmt)])
            counts = {key: sum(v.startswith(key) for v in verdicts)
                      for key in ("accepted", "refused", "crash", "hang", "runaway", "uncaught")}
            print(f"{fmt:6s} {len(verdicts):6d} {counts['accepted']:9d} {counts['refused']:8d} {counts['crash']:8d} "
                  f"{counts['hang']:6d} {counts['runaway']:9d} {payloads:9d} {counts['uncaught']:17d} "
                  f"{time.monotonic() - started:8.0f}", flush=True)
            for (_, path), verdict in zip(paths, verdicts):
                if not verdict.startswith(("accepted", "refused")):
                    print(f"    {Path(path).name}: {verdict}", flush=True)


def big_png(width: int, height: int) -> bytes:
    """An RGB PNG of zeros: a few hundred KB that decode to width x height x 3 bytes."""
    compressor = zlib.compressobj(9)
    row = b"\0" * (1 + 3 * width)
    data = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", data) + chunk(b"IEND", b"")


if __name__ == "__main__":
    main()
