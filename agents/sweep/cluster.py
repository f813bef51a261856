"""Where a `bh8 sweep` runs: what one trial reserves (--resources-per-trial), the Ray cluster it
joins (--address, checked to answer before ray.init, which would retry for minutes) or the local
Ray it starts."""
from __future__ import annotations

import argparse
import ipaddress
import os
import re
import socket
import threading

from bh8_gym.agents.training import config_check
from bh8_gym.agents.sweep.space import SweepConfigError

# The largest amount of a resource one trial may reserve (CPUs, GPUs, memory in bytes, custom units).
RESOURCE_LIMITS = {"cpu": 1024.0, "gpu": 64.0, "memory": float(2**50)}
CUSTOM_RESOURCE_LIMIT = 1e6
MAX_CPUS = 4096  # --num-cpus of a local Ray
# How long `--address` may take to answer before the sweep gives up (a port that is not a Ray head's
# would otherwise keep ray.init retrying for minutes).
CONNECT_TIMEOUT_S = 15.0


def resources_argument(text: str) -> dict[str, float]:
    """argparse `type=` for --resources-per-trial: "cpu=2", "cpu=1,gpu=0.5", custom resources too."""
    try:
        return check_resources(_parse_resources(text))
    except SweepConfigError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _parse_resources(text: str) -> dict[str, float]:
    resources: dict[str, float] = {}
    usage = f"expected NAME=AMOUNT pairs such as cpu=2 or cpu=1,gpu=0.5, got {text[:100]!r}"
    if len(text) > 10_000:
        raise SweepConfigError(usage)
    for item in text.split(","):
        name, equals, value = item.strip().partition("=")
        try:
            amount = float(value)
        except ValueError:
            raise SweepConfigError(usage) from None
        if not equals or not re.fullmatch(r"[A-Za-z_][\w.:/-]{0,99}", name) or name in resources:
            raise SweepConfigError(usage)
        resources[name.lower() if name.lower() in RESOURCE_LIMITS else name] = amount
    resources.setdefault("cpu", 1.0)
    return resources


def check_resources(resources) -> dict[str, float]:
    """What one trial reserves: each amount finite, in 0..its limit (RESOURCE_LIMITS; custom
    resources CUSTOM_RESOURCE_LIMIT), and some CPU."""
    if not isinstance(resources, dict) or not resources or len(resources) > 100:
        raise SweepConfigError(f"expected NAME=AMOUNT pairs, got {config_check.shown(resources)}")
    for name, amount in resources.items():
        limit = RESOURCE_LIMITS.get(name, CUSTOM_RESOURCE_LIMIT)
        if (not isinstance(name, str) or isinstance(amount, bool) or not isinstance(amount, (int, float))
                or not 0 <= amount <= limit):
            raise SweepConfigError(f"{config_check.shown(name)}={config_check.shown(amount)} is out of range (each "
                                   f"amount a number in 0..{limit:g})")
    if not resources.get("cpu", 0) > 0:
        raise SweepConfigError(f"a trial needs at least some CPU (cpu > 0), got {config_check.shown(resources)}")
    return {name: float(amount) for name, amount in resources.items()}


def address_argument(text: str) -> str:
    """argparse `type=` for --address: "auto", HOST:PORT, [IPV6]:PORT or ray://HOST:PORT with the
    port in 1..65535 (only the syntax here; `check_reachable` tries it)."""
    if text == "auto":
        return text
    if _host_and_port(text) is None:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with a port in 1..65535 (e.g. 10.0.0.5:6379 or "
                                         f"[::1]:6379), ray://HOST:PORT or auto, got {text[:200]!r}")
    return text


def _host_and_port(address: str) -> tuple[str, int] | None:
    rest = address[len("ray://"):] if address.startswith("ray://") else address
    found = re.fullmatch(r"\[([0-9A-Fa-f:.]{2,45})\]:([0-9]{1,5})|([A-Za-z0-9][A-Za-z0-9.-]{0,252}):([0-9]{1,5})", rest)
    if found is None:
        return None
    host, port = (found.group(1), found.group(2)) if found.group(1) else (found.group(3), found.group(4))
    if found.group(1):
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            return None
    return (host, int(port)) if 1 <= int(port) <= 65535 else None


def check_reachable(address: str, timeout: float | None = None) -> None:
    """Fail fast, with a message, when --address cannot be a running Ray head: nothing listens on
    the port, or what listens is not a Ray head's GCS (ray.init would retry either for minutes)."""
    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    if address == "auto":
        return  # ray.init finds the cluster started on this machine, or says at once that there is none
    host, port = _host_and_port(address)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as error:
        raise SweepConfigError(f"cannot reach the Ray cluster at {address!r}: {error.strerror or error} (is "
                               "`ray start --head` running there, and is this the port it printed?)") from None
    if address.startswith("ray://"):
        return
    try:  # Ray's own GCS client, as ray.init uses it, in a thread the sweep can give up on
        from ray._raylet import GcsClient
    except ImportError:
        return
    answered = threading.Event()

    def ask() -> None:
        try:
            GcsClient(address=f"{host}:{port}" if ":" not in host else f"[{host}]:{port}").cluster_id  # noqa: B018
        except Exception:  # noqa: BLE001 (any answer, even a refusal, is Ray's: ray.init will say what it is)
            pass
        answered.set()

    threading.Thread(target=ask, daemon=True, name="bh8-sweep-address-check").start()
    if not answered.wait(timeout):
        raise SweepConfigError(f"no Ray cluster answered at {address!r} within {timeout:g} s (is it the port "
                               "`ray start --head` printed? A cluster with token authentication also needs "
                               "RAY_AUTH_MODE=token and its token here, docs/cluster.md)")


def start_ray(args: argparse.Namespace, settings: dict) -> bool:
    """Join --address or start Ray here; True if this process started it (and shuts it down)."""
    import ray

    if ray.is_initialized():
        return False
    try:
        if args.address:
            ray.init(address=args.address, log_to_driver=True)  # reachable: `check_reachable`
        else:
            # "local": a Ray of its own even when `ray start` left one running here (that one: --address auto)
            ray.init(address="local", num_cpus=args.num_cpus or os.cpu_count() or 1, include_dashboard=False)
    except Exception as error:  # noqa: BLE001 (Ray raises plain Exception when its node does not come up)
        where = f"the Ray cluster at {args.address!r}" if args.address else "a local Ray"
        hint = ("; a cluster with token authentication (Ray's default once ~/.ray/auth_token exists) also needs "
                "RAY_AUTH_MODE=token and its token here (docs/cluster.md)") if args.address else ""
        said = (str(error).strip().splitlines() or [type(error).__name__])[0][:300]
        raise SweepConfigError(f"cannot start or join {where}: {said}{hint}") from None
    total = ray.cluster_resources()
    names = {"cpu": "CPU", "gpu": "GPU"}  # Ray's names in cluster_resources()
    short = {name: amount for name, amount in settings["resources"].items()
             if amount > total.get(names.get(name, name), 0.0)}
    if short:
        ray.shutdown()
        raise SweepConfigError("--resources-per-trial asks for more than the whole cluster has: " + ", ".join(
            f"{name}={amount:g} > {total.get(names.get(name, name), 0.0):g}" for name, amount in short.items()))
    return True
