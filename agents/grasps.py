"""The scripted LOOP grasps, host side: each reads only the feedback blocks and writes LOOP bytes,
so the same object runs in an env, in `bh8 deploy` on a real hand, and as a candidate of the grasp
choice (`agents/choice/`). `bh8 eval --baseline` runs them (`agents/evaluation/baselines.py` adds the
supervisory grasp, which needs the firmware).

`LoopBaseline`: the spread driven to its setting by a proportional law on LFAP, then constant
closing velocity bytes with a constant gain on the fingers (the gain byte sets the grasp force, §6.1).
`SqueezeBaseline`: close until contact, then squeeze to a strain target. `Hold`: LCV 0 on the
fingers, whose worms keep the squeeze they have (§9.3.1), the spread held: what a grasp switches to
once it has closed far enough.

The spread: F1 and F2 opposite F3 (spread 0, a two-against-one wrap) for every object, so no
script needs to know what it grasps. The tripod (60°) a BH8 user might set for a ball held none of
the 20 validation spheres from the palm-down approach (the first finger to touch rolls the ball
away), against 11-14 of 20 at spread 0 (`mixed-validation`, 200 episodes from seed 20000).
"""
from __future__ import annotations

import numpy as np

from bh8_gym.action_bytes import byte_list_to_unit, centres_and_halves
from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

GRASP_SPREAD = 0  # encoder counts: F1 and F2 opposite F3 (module docstring)


def clamp(value, low, high):
    """`value` within [low, high] (NaN stays NaN): np.clip costs ~3 µs on one number, every cycle."""
    return low if value < low else (high if value > high else value)


def host_side(env):
    """The host's side a LOOP script reads: an env's `LoopInterface` (through the env's attributes)
    or the interface itself (`bh8 deploy`, which has no env): layout, byte space, cycle time, safety."""
    return getattr(env, "unwrapped", env)


def grasp_seconds(host) -> float:
    """The arm's grasp phase (seconds) for an env or a grasp `LoopInterface` (its task is the arm's phase)."""
    arm = getattr(host, "arm", None) or host.task.arm
    return float(arm.grasp_seconds)


class _LoopScript:
    """What the scripted LOOP grasps share: the env's layout, its byte space, and the bytes a script
    sets each cycle turned into the float action of the env's ContinuousActions view. `env` is an
    env or its `LoopInterface` (`host_side`): a script reads only the host's side."""

    def __init__(self, env):
        base = host_side(env)
        self.layout = base.layout
        space = base.action_space  # the env's byte space; the policy speaks floats of ContinuousActions
        self._low, self._high = space.low.tolist(), space.high.tolist()
        self._centres, self._halves = centres_and_halves(space.low, space.high)
        self._control_fields = self.layout.control_fields
        self._bytes = np.zeros(len(self._control_fields), dtype=np.int64)

    def _action(self) -> np.ndarray:
        # within the env's byte space (the safety envelope clamps LCV): the action the env will run
        values = [clamp(value, low, high) for value, low, high in zip(self._bytes.tolist(), self._low, self._high)]
        return np.array(byte_list_to_unit(values, self._centres, self._halves), dtype=np.float32)


class StalledFingers:
    """The host's view of a finger's stall (§5.5 case 1 at the default TSTOP): its LFAP has closed
    `start_counts` and then moved less than `counts` in `window_s`. A stalled finger stays stalled:
    a script gives it LCV 0 from then on and its worm holds it with the squeeze it had (§9.3.1; App. B
    A1: "the motor current may be removed since the finger joints become mechanically locked")."""

    WINDOW_S, COUNTS, START_COUNTS = 0.03, 10, 1000

    def __init__(self, motors=FINGER_MOTORS):
        self.motors = tuple(motors)
        self.reset()

    def reset(self) -> None:
        self.stalled = {m: False for m in self.motors}
        self._history = []  # (time, {finger: LFAP}) back to the newest entry at least WINDOW_S old

    def update(self, now: float, positions: dict) -> dict:
        """Notes the fingers' LFAP at host time `now` (s); returns `stalled` (finger -> bool)."""
        history = self._history
        history.append((now, dict(positions)))
        while len(history) > 1 and now - history[1][0] >= self.WINDOW_S:
            history.pop(0)
        then, before = history[0]
        if now - then >= self.WINDOW_S:
            for m in self.motors:
                if positions[m] >= self.START_COUNTS and abs(positions[m] - before[m]) < self.COUNTS:
                    self.stalled[m] = True
        return self.stalled


class LoopBaseline(_LoopScript):
    """Constant closing velocity and gain on the fingers; P control of the spread on LFAP.

    Byte values: `close_velocity` LCV (×LCVC/16 counts per sample; the safety envelope's 100 at
    LCVC 1 is ~6.3 counts per 256 µs sample, the fastest close it allows), `gain` LCPG (force at
    stall ∝ gain × velocity error, §6.1), `spread_gain` bytes of LCV per count of spread error,
    `spread_tolerance` counts within which the fingers start closing, `spread` its setting
    (counts). The defaults are the best of a sweep on the validation objects (`mixed-validation`,
    100 episodes each from seed 20000, spheres at a 60° spread then: gain 255 65 %, 60 48 %, 40 41 %;
    200 episodes: gain 255 59 %, close velocity 60 54 %; every object at spread 0: 65 %): the grasp
    phase is 0.8 s, and the squeeze through the lift is gain × commanded velocity, which at gain 255
    passes the strain limit in about one episode in ten (a safety stop, counted as a failure).
    `lock_stalled`: LCV 0 for a finger once it has stalled (`StalledFingers`), so its worm holds the
    squeeze it had instead of the motor working its links against the object (on `primitives-validation`,
    100 episodes from seed 100000: 76 held against 73 driven on, every one of those 73 among them).
    Off by default: every figure of the `loop` grasp (the README, the ceiling) was measured driven on.
    """

    def __init__(self, env, close_velocity: int = 100, gain: int = 255, spread_gain: float = 0.1,
                 spread_tolerance: int = 30, spread: int = GRASP_SPREAD, strain_limit: int | None = None,
                 limit_gain: float = 2.0, capped_gain: int | None = None, lock_stalled: bool = False):
        super().__init__(env)
        self.stalls = StalledFingers() if lock_stalled else None
        self.spread = int(spread)
        self.close_velocity, self.gain = int(close_velocity), int(gain)
        self.spread_gain, self.spread_tolerance = float(spread_gain), int(spread_tolerance)
        self.strain_limit = None if strain_limit is None else int(strain_limit)
        self.limit_gain = float(limit_gain)
        #: With `strain_limit`: a finger over the limit gets this gain byte instead of backing off
        #: its velocity (None: back off the velocity, keep the gain).
        self.capped_gain = None if capped_gain is None else int(capped_gain)
        feedback = self.layout.feedback_fields
        self._spread_position = next((i for i, (m, name) in enumerate(feedback)
                                      if m == SPREAD_MOTOR and name == "LFAP"), None)
        self._strain_index = {m: feedback.index((m, "LFS")) for m in FINGER_MOTORS if (m, "LFS") in feedback}
        self._finger_position = {m: feedback.index((m, "LFAP")) for m in FINGER_MOTORS} if lock_stalled else {}
        self.reset(env)

    def reset(self, env) -> None:
        self.spread_position = 0  # HI leaves the spread at 0 (SPEC.md §4)
        self._cycles = 0  # the host's clock: cycles of the episode's length (randomised per reset)
        self.cycle_seconds = host_side(env).cycle_seconds
        if self.stalls is not None:
            self.stalls.reset()

    def act(self, observation, info=None) -> np.ndarray:
        block = (info or {}).get("feedback_block")
        values = self.layout.decode_feedback(block) if block else None
        if values and self._spread_position is not None:
            self.spread_position = values[self._spread_position]
        spread_error = self.spread - self.spread_position
        spread_ready = abs(spread_error) <= self.spread_tolerance
        self._cycles += 1
        stalled = {}
        if values and self.stalls is not None:
            stalled = self.stalls.update(self._cycles * self.cycle_seconds,
                                         {m: values[i] for m, i in self._finger_position.items()})
        for index, (motor, name) in enumerate(self._control_fields):
            if motor == SPREAD_MOTOR:
                value = (int(clamp(self.spread_gain * spread_error, -127, 127)) if name == "LCV"
                         else self.gain)
            else:
                over = (self.strain_limit is not None and values is not None and motor in self._strain_index
                        and values[self._strain_index[motor]] > self.strain_limit)
                if name == "LCV":
                    value = self.close_velocity if spread_ready and not stalled.get(motor) else 0
                    if over and self.capped_gain is None:  # over the limit, back off in proportion
                        value = min(value, int(self.limit_gain * (self.strain_limit - values[self._strain_index[motor]])))
                else:
                    value = self.capped_gain if over and self.capped_gain is not None else self.gain
            self._bytes[index] = value
        return self._action()


class SqueezeBaseline(_LoopScript):
    """Close until contact, finger by finger, then squeeze to a strain target: the best LOOP grasp
    we could script from the host's feedback (LFS strain and LFAP position per finger).

    Closing: every finger at `close_velocity` with gain `close_gain`. A finger whose strain has
    risen `contact_rise` over its own reading at reset in two cycles running (one cycle's reading
    swings ±13 counts as a finger starts), or which has stalled (moved less than `stall_counts` in
    `stall_cycles` cycles), is in contact: it holds (LCV 0; the worm drive keeps
    it there) until every finger is in contact or the grasp phase is `squeeze_after` through. Then
    each finger squeezes: LCV = `squeeze_gain` × (strain target − strain), clipped to
    ±`squeeze_velocity`, gain `hold_gain`, so the grip stays under the safety envelope's strain
    limit through the lift and hold. The spread is held at `spread` (counts) with gain byte
    `spread_hold_gain`: the spread is back-driven by the grasp (SPEC.md §1), and held softly it opened
    to 300 counts under a squeezed capsule, which then slipped out.

    The gains are the best of a sweep on the validation objects (`mixed-validation`, seeds from
    20000; 100 episodes: close/hold gain 25/80 55 %, 40/60 56 %, 40/80 61 %, 40/120 60 %, 60/80
    68 %; 200 episodes: 60/80 59 %, 90/80 56.5 %, 130/80 53 %, 255/80 56 %, 255/255 41.5 % with a
    safety stop in one episode of four; all with spheres at a 60° spread and the spread held at the
    hold gain). A lower strain target (180) lost 15 points; hold gain 160 with strain target 220
    48 %. Spread 0 for every object: 64 %; and held at gain 255: 66.5 %, the default.
    """

    def __init__(self, env, close_velocity: int = 100, close_gain: int = 60, contact_rise: int = 10,
                 stall_counts: int = 40, stall_cycles: int = 6, squeeze_after: float = 0.7,
                 strain_target: int = 205, squeeze_gain: float = 1.0, squeeze_velocity: int = 40,
                 hold_gain: int = 80, spread_gain: float = 0.1, spread: int = GRASP_SPREAD,
                 spread_hold_gain: int = 255, wrap_velocity: int | None = None, wrap_gain: int = 255,
                 spread_tolerance: int = 30):
        super().__init__(env)
        #: Instead of squeezing to the strain target once every finger touches: keep closing every
        #: finger at this velocity with `wrap_gain` (the outer links break away and wrap round
        #: the object, §9.3). None: squeeze.
        self.wrap_velocity = None if wrap_velocity is None else int(wrap_velocity)
        self.wrap_gain = int(wrap_gain)
        self.spread_tolerance = int(spread_tolerance)
        base = host_side(env)
        self.close_velocity, self.close_gain = int(close_velocity), int(close_gain)
        self.contact_rise, self.stall_counts, self.stall_cycles = int(contact_rise), int(stall_counts), int(stall_cycles)
        self.squeeze_after = float(squeeze_after)
        self.strain_target = min(int(strain_target), base.safety.max_strain - 10)
        self.squeeze_gain, self.squeeze_velocity = float(squeeze_gain), int(squeeze_velocity)
        self.hold_gain, self.spread_gain = int(hold_gain), float(spread_gain)
        self.spread, self.spread_hold_gain = int(spread), int(spread_hold_gain)
        self._cycle_seconds = float(base.cycle_seconds)
        self._grasp_seconds = grasp_seconds(base)
        feedback = self.layout.feedback_fields
        self._strain_index = {m: feedback.index((m, "LFS")) for m in FINGER_MOTORS if (m, "LFS") in feedback}
        self._position_index = {m: feedback.index((m, "LFAP")) for m in (*FINGER_MOTORS, SPREAD_MOTOR)
                                if (m, "LFAP") in feedback}
        self.reset(env)

    def reset(self, env) -> None:
        self.zero = None
        self.contact = {m: False for m in FINGER_MOTORS}
        self.history = {m: [] for m in FINGER_MOTORS}
        self.rising = {m: 0 for m in FINGER_MOTORS}  # cycles running with the strain risen
        self.cycles = 0
        self.started = False  # the fingers close once the spread is at its setting

    def act(self, observation, info=None) -> np.ndarray:
        block = (info or {}).get("feedback_block")
        values = self.layout.decode_feedback(block) if block else None
        strain = {m: values[i] for m, i in self._strain_index.items()} if values else {}
        position = {m: values[i] for m, i in self._position_index.items()} if values else {}
        if self.zero is None:
            self.zero = dict(strain)
        spread_error = self.spread - position.get(SPREAD_MOTOR, 0)
        # The fingers wait for the spread to reach its setting (a finger closing while the spread
        # turns stalls against its neighbour and would read as a contact).
        self.started = self.started or abs(spread_error) <= self.spread_tolerance
        for m in FINGER_MOTORS:
            if not self.started:
                break
            if m in position:
                self.history[m].append(position[m])
            if not self.contact[m]:
                risen = strain.get(m, 0) - self.zero.get(m, 0) >= self.contact_rise
                self.rising[m] = self.rising[m] + 1 if risen else 0
                past = self.history[m][-self.stall_cycles - 1:]
                stalled = len(past) > self.stall_cycles and past[-1] - past[0] < self.stall_counts
                self.contact[m] = self.rising[m] >= 2 or stalled
        squeezing = all(self.contact.values()) or self.cycles * self._cycle_seconds >= self.squeeze_after * self._grasp_seconds
        self.cycles += 1
        for index, (motor, name) in enumerate(self._control_fields):
            if motor == SPREAD_MOTOR:
                value = (int(clamp(self.spread_gain * spread_error, -127, 127)) if name == "LCV"
                         else self.spread_hold_gain)
            elif squeezing and self.wrap_velocity is not None:
                value = self.wrap_velocity if name == "LCV" else self.wrap_gain
            elif squeezing:
                error = self.strain_target - strain.get(motor, self.strain_target)
                value = (int(clamp(self.squeeze_gain * error, -self.squeeze_velocity, self.squeeze_velocity))
                         if name == "LCV" else self.hold_gain)
            elif self.contact[motor] or not self.started:
                value = 0 if name == "LCV" else (self.hold_gain if self.started else self.close_gain)
            else:
                value = self.close_velocity if name == "LCV" else self.close_gain
            self._bytes[index] = value
        return self._action()


SPREAD_60 = 1050  # encoder counts: 60° of the spread's 180° over 3,150 counts (SPEC.md §1)

# The ceiling family (agents/evaluation/ceiling.py measures it): name -> (baseline, its settings). Every script is
# object-blind: it reads only the feedback blocks.
FAMILY: dict[str, tuple[str, dict]] = {
    "loop": ("loop", {}),
    "loop-g80": ("loop", {"gain": 80}),
    "loop-g160": ("loop", {"gain": 160}),
    "loop-v50": ("loop", {"close_velocity": 50}),
    "loop-v50-g80": ("loop", {"close_velocity": 50, "gain": 80}),
    "loop-v70": ("loop", {"close_velocity": 70}),
    "loop-s60": ("loop", {"spread": SPREAD_60}),
    "loop-v50-s60": ("loop", {"close_velocity": 50, "spread": SPREAD_60}),
    "squeeze": ("squeeze", {}),
    "squeeze-g255": ("squeeze", {"close_gain": 255}),  # closes as "loop" does until each finger touches
    "squeeze-t180": ("squeeze", {"strain_target": 180}),
    "squeeze-t225": ("squeeze", {"strain_target": 225}),
    "squeeze-v50": ("squeeze", {"close_velocity": 50}),
    "squeeze-soft": ("squeeze", {"close_gain": 40, "hold_gain": 60}),
    "squeeze-firm": ("squeeze", {"close_gain": 120, "hold_gain": 160}),
    "squeeze-s60": ("squeeze", {"spread": SPREAD_60}),
}


class Hold(_LoopScript):
    """Every finger LCV 0 with gain `gain` (its worm keeps the squeeze it has, §9.3.1; App. B A1), the
    spread held at `spread` by the LOOP scripts' proportional law with gain byte 255: a grasp the
    choice switches to once the fingers have closed on the object (from the start it never closes)."""

    def __init__(self, env, gain: int = 80, spread: int = GRASP_SPREAD, spread_gain: float = 0.1):
        super().__init__(env)
        self.gain, self.spread, self.spread_gain = int(gain), int(spread), float(spread_gain)
        self._spread_position = self.layout.feedback_fields.index((SPREAD_MOTOR, "LFAP"))

    def reset(self, env=None) -> None:
        """Nothing to forget: the hold reads only the newest block."""

    def act(self, observation, info=None) -> np.ndarray:
        values = self.layout.decode_feedback(info["feedback_block"])
        spread_error = self.spread - values[self._spread_position]
        for index, (motor, name) in enumerate(self._control_fields):
            if motor == SPREAD_MOTOR:
                self._bytes[index] = int(clamp(self.spread_gain * spread_error, -127, 127)) if name == "LCV" else 255
            else:
                self._bytes[index] = 0 if name == "LCV" else self.gain
        return self._action()


LOOP_SCRIPTS = {"loop": LoopBaseline, "squeeze": SqueezeBaseline, "hold": Hold}

# Grasps that only make sense after another one has closed the fingers (the grasp choice's
# continuations): name -> (script, its settings), as FAMILY.
CONTINUATIONS: dict[str, tuple[str, dict]] = {
    "hold": ("hold", {}),
    "hold-g255": ("hold", {"gain": 255}),
}


def make_loop_script(kind: str, env, **settings):
    """A LOOP script of `kind` ("loop", "squeeze", "hold") for `env` (an env or its LoopInterface);
    `settings` are its class's keyword arguments (a TypeError names a wrong one)."""
    if kind not in LOOP_SCRIPTS:
        raise ValueError(f"unknown LOOP script {kind!r} (known: {', '.join(LOOP_SCRIPTS)})")
    try:
        return LOOP_SCRIPTS[kind](env, **settings)
    except TypeError as error:
        raise ValueError(f"script {kind!r}: {error}") from None


def make_script(name: str, env):
    """The named grasp `name` (the ceiling family's, or a continuation's) for `env`."""
    if name in FAMILY:
        kind, settings = FAMILY[name]
    elif name in CONTINUATIONS:
        kind, settings = CONTINUATIONS[name]
    else:
        raise ValueError(f"unknown script {name!r} (the family: {', '.join(FAMILY)}; continuations: "
                         f"{', '.join(CONTINUATIONS)})")
    return make_loop_script(kind, env, **settings)


def run_script(env, script, seed: int) -> bool:
    """One episode of `script` (anything with `reset(env)` and `act(observation, info)`: a LOOP script,
    a grasp-choice policy) on `seed`; whether it held the object."""
    observation, info = env.reset(seed=seed)
    script.reset(env)
    done = False
    while not done:
        observation, _, terminated, truncated, info = env.step(script.act(observation, info))
        done = terminated or truncated
    return bool(info.get("is_success"))
