"""The scripted baselines of `bh8 eval --baseline NAME`: the LOOP scripts (`agents/grasps.py`, host
side) and the supervisory grasp, which talks GCL to the env's firmware.

`SupervisoryBaseline`: leave LOOP, set the spread (SM), close with TC (or C), then
re-enter LOOP with zero velocity and zero gain (the finger worm drives hold the grasp unpowered,
SPEC.md §1) while the arm lifts. Every command is GCL bytes written to the env's firmware, as a
host would send them over the cable.
"""
from __future__ import annotations

import numpy as np

from bh8_gym.action_bytes import bytes_to_unit
from bh8_gym.agents.grasps import FAMILY, GRASP_SPREAD, make_loop_script, make_script
from bh8_gym.loop_interface import END_TOLERANCE_S


class SupervisoryBaseline:
    """SM (spread), GTC or GC, then hold (LOOP, zero velocity and gain) while the arm lifts."""

    def __init__(self, env, close_command: str = "GTC", spread: int = GRASP_SPREAD):
        self.spread = int(spread)
        if close_command not in ("GTC", "GC"):
            raise ValueError(f"close_command must be 'GTC' or 'GC', got {close_command!r}")
        self.close_command = close_command
        base = env.unwrapped
        self.loop_command = base.loop_command
        self._hold = np.zeros(base.action_space.shape, dtype=np.float32)
        # zero velocity and zero gain (LCPG 0 = no torque, SPEC.md §5) in the float action space
        self._hold[:] = bytes_to_unit(np.zeros(base.action_space.shape), base.action_space.low.astype(float),
                                      base.action_space.high.astype(float))

    def _command(self, firmware, line: str) -> bytes:
        reply = firmware.transact(line.encode("ascii") + b"\r")
        if b"ERR" in reply and not line.startswith("\x03"):
            raise RuntimeError(f"supervisory baseline: {line!r} failed: {reply!r}")
        return reply

    def run_episode(self, env, seed: int, tracker, frames=None, every: int = 1):
        """One episode: returns (return, steps, last info, supervisory seconds, grasp seconds)."""
        obs, info = env.reset(seed=seed)
        base = env.unwrapped
        firmware = base.firmware
        if frames is not None:
            frames.append(env.render())
        start = firmware.time
        firmware.transact(b"\x03")  # leave LOOP: the hand answers with a prompt
        self._command(firmware, f"SM {self.spread}")
        self._command(firmware, self.close_command)
        grasp_seconds = firmware.time - start
        if tracker is not None:
            strains = self._command(firmware, "GFGET SG").split(b"\n\r")[1].split()
            tracker.observe_strains(np.array([int(s) for s in strains]))
        firmware.write(self.loop_command.encode("ascii") + b"\r")
        firmware.run_until_idle()
        firmware.read()
        # The arm waits for the close (a user's script lifts after C returns): move the arm's clock
        # so its schedule is at the start of the lift.
        base.scene.start_time = firmware.time - base.scene.arm.grasp_seconds
        # ... and the episode ends with the arm's schedule, as the LOOP policies' do: the env's own
        # clock (2 s of cycles from LOOP entry) would hold the object through the grasp time again.
        schedule_end = base.scene.start_time + base.scene.arm.total_seconds - END_TOLERANCE_S
        total, steps, done = 0.0, 0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(self._hold)
            if tracker is not None:
                tracker.observe(info.get("feedback_block"))
            total += float(reward)
            steps += 1
            done = terminated or truncated or firmware.time >= schedule_end
            if frames is not None and (steps % every == 0 or done):
                frames.append(env.render())
        return total, steps, info, grasp_seconds, grasp_seconds


BASELINES = ("supervisory", "loop", "squeeze")
LOOP_BASELINES = ("loop", "squeeze")  # policies on the env's action space: act(observation, info)


def make_baseline(name: str, env, **settings):
    """One of BASELINES for `env` (a ContinuousActions-wrapped BH8Grasp env); `settings` are the
    class's keyword arguments (a TypeError names a wrong one)."""
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r} (known: {', '.join(BASELINES)})")
    if name in LOOP_BASELINES:
        return make_loop_script(name, env, **settings)
    try:
        return SupervisoryBaseline(env, **settings)
    except TypeError as error:
        raise ValueError(f"baseline {name!r}: {error}") from None


def make_grasp(name: str, env):
    """A scripted grasp by the name `bh8 eval --baseline` takes: the family's script `name` if there
    is one, else the baseline `name`, for `env`."""
    return make_script(name, env) if name in FAMILY else make_baseline(name, env)
