"""How firmly the simulated hand holds what it grasps (manual §9.3.1: worm drives do not back-drive;
App. B FAQ A1: the grasp stays with the motor current removed).

Per trial: a palm-down hand at the defaults (HI, HOLD 0 on the fingers) over an object standing on
the table, placed as the grasp env places it: the knuckles 1-3 cm above the object's top (the palm
face at least 115 mm above the table), with the arm's error (±2 cm, ±15° yaw); `GC`; the arm lifts the hand
10 cm in 0.7 s (minimum jerk) and holds it still for 5 s (`--shake`: shaken ±1 cm at 2 Hz instead).
For each shape: cylinders, boxes, spheres and capsules of three sizes spanning the env's graspable
range, masses and frictions drawn from its ranges, 15 placements per size (45 trials per shape).

`--mode loop`: the grasp a policy drives instead of GC: the env's LOOP (BH8Grasp-v0's setup script,
38400 baud, one control block per cycle), every finger LCV 100 (the safety envelope's fastest) at
gain 255 and the spread held at 0 (`LoopBaseline`'s law on LFAP, LCV `--spread-gain` x its error,
gain 255) from the first cycle to the last: 0.8 s of grasp (the env's grasp phase), then the same
lift and hold, the arm moved once per cycle as the env's arm is. A finger whose LFAP has closed
1000 counts and then moved less than 10 counts in 30 ms (the host's view of §5.5's stall) gets LCV 0
from then on: its worm holds it with the squeeze it had (§9.3.1, App. B A1: "the motor current may
be removed since the finger joints become mechanically locked"); `--drive-stalled` drives it on at
LCV 100 to the end, which lets a pinched object creep about the pinch (tests/test_bench_hold.py).
Its extra column counts the grasps whose strain went over the safety envelope's limit (230) in some
cycle, where the env would have stopped them (they are measured on).

Printed per shape:
* closed: grasps that close on the object: when GC ends F3 and F1 or F2 (which stand side by side
  opposite F3) touch it; "all 3": every finger does;
* kept: of the closed ones, the object still in the hand after the hold (within 3 cm of where the
  lift left it, and off the table);
* squeeze kept: of those kept, the gauges' summed load at the end of the hold is at least 70 % of
  what it was when GC ended (the gauges sense the outer joints only);
* slip and rotation of the object in the wrist frame from the end of the lift to the end of the hold
  (median and max, over the closed grasps that kept it);
* GC's end after the last finger's last contact, over the grasps in which every finger stops on the
  object (median, max, and the share within TSTOP + 0.2 s): §5.5 says a motor stops TSTOP after it
  stalls. A finger's last contact is its first touch or, if its clutch breaks away after that, when
  its outer link, which the motor then drives on alone (§9.3.1), meets the object (the breakaway
  itself if the outer link already touches it, or never does): a new motion, not a late stall. A
  finger that slips past the object and closes to CT ends on its goal (§5.5 case 3), not on a stall:
  such grasps are not counted.

Run: python benchmarks/bench_hold.py [--mode gc|loop] [--shapes cylinder box] [--placements 15] [--shake] [--jobs 2]
     [--spread-gain 0.1] [--drive-stalled]
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
import pybullet as p

from bh8_gym.agents.grasps import StalledFingers
from bh8_gym.envs.interfaces import grasp_interface
from bh8_gym.firmware import Firmware
from bh8_gym.hand_urdf import KNUCKLE_HEIGHT, PALM_TOP
from bh8_gym.objects import ObjectSpec, add_object
from bh8_gym.plant import HandPlant, PlantParameters
from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR
from bh8_gym.safety import SafetyEnvelope

PALM_DOWN = (1.0, 0.0, 0.0, 0.0)
SHAPES = ("cylinder", "box", "sphere", "capsule")
SIZES = (0.04, 0.06, 0.08)  # m: diameter or side, across the env's 3-9 cm primitives
HEIGHT = 0.09  # m: standing cylinders, boxes and capsules (the env's largest extent)
MASS_RANGE = (0.05, 0.40)  # kg (envs.objects.PrimitiveRanges)
FRICTION_RANGE = (0.4, 1.2)
POSITION_ERROR = 0.02  # m, envs.scenes.PlacementRanges
YAW_ERROR = math.radians(15.0)
CLEARANCE = (0.01, 0.03)  # m between the knuckles and the object's top (envs.scenes.PlacementRanges)
MIN_PALM_ABOVE_TABLE = 0.115
LIFT_HEIGHT, LIFT_SECONDS, HOLD_SECONDS = 0.10, 0.7, 5.0
SHAKE_AMPLITUDE, SHAKE_HZ = 0.01, 2.0
GC_LIMIT_S = 30.0
KEPT_DISTANCE = 0.03  # m: further than this from the lifted pose, the object was lost
TSTOP_S = 0.030  # the default TSTOP
CT_COUNTS = 17_000  # the default CT: a finger this close to it (within CT_MARGIN) closed past the object
CT_MARGIN = 100
MODES = ("gc", "loop")
LOOP_CLOSE_VELOCITY, LOOP_GAIN = 100, 255  # LCV (the safety envelope's fastest) and LCPG bytes
LOOP_GRASP_S = 0.8  # the env's grasp phase (envs.arm.ArmSchedule.grasp_seconds)
SPREAD_GAIN = 0.1  # LCV bytes per count of spread error (agents.grasps.LoopBaseline)


@dataclass(frozen=True)
class Trial:
    shape: str
    size: float
    mass: float
    friction: float
    offset: tuple[float, float]
    yaw: float
    clearance: float
    shake: bool = False
    mode: str = "gc"
    spread_gain: float = SPREAD_GAIN  # --mode loop: LCV bytes per count of spread error
    lock_stalled: bool = True  # --mode loop: LCV 0 for a finger once it has stalled


def trials(shapes, placements: int, shake: bool, seed: int = 0, mode: str = "gc", spread_gain: float = SPREAD_GAIN,
           lock_stalled: bool = True) -> list[Trial]:
    rng = np.random.default_rng(seed)
    out = []
    for shape in shapes:
        for size in SIZES:
            for _ in range(placements):
                offset = tuple(float(v) for v in rng.uniform(-POSITION_ERROR, POSITION_ERROR, 2))
                out.append(Trial(shape, size, float(rng.uniform(*MASS_RANGE)), float(rng.uniform(*FRICTION_RANGE)),
                                 offset, float(rng.uniform(-YAW_ERROR, YAW_ERROR)), float(rng.uniform(*CLEARANCE)), shake,
                                 mode, spread_gain, lock_stalled))
    return out


def _object(plant: HandPlant, trial: Trial) -> tuple[int, float]:
    """The object standing on the table under the palm; returns (body, height)."""
    shape, size = trial.shape, trial.size
    if shape == "box":
        kind, dims, height = "box", (size, size, HEIGHT), HEIGHT
    elif shape == "cylinder":
        kind, dims, height = "cylinder", (size, HEIGHT), HEIGHT
    elif shape == "sphere":
        kind, dims, height = "sphere", (size,), size
    else:  # full extents: diameter, whole length (caps included)
        kind, dims, height = "capsule", (size, max(HEIGHT, size + 1e-3)), max(HEIGHT, size + 1e-3)
    yaw = (0.0, 0.0, math.sin(trial.yaw / 2), math.cos(trial.yaw / 2))
    body = add_object(plant, ObjectSpec(kind, dims, mass=trial.mass, friction=trial.friction),
                      position=(trial.offset[0], trial.offset[1], height / 2 + 1e-4), orientation=yaw)
    return body, height


def _relative_pose(plant: HandPlant, body: int):
    wrist_position, wrist_orientation = plant.wrist_pose()
    position, orientation = plant.object_pose(body)
    inverse = p.invertTransform(wrist_position.tolist(), wrist_orientation.tolist())
    relative = p.multiplyTransforms(inverse[0], inverse[1], position.tolist(), orientation.tolist())
    return np.array(relative[0]), np.array(relative[1])


def run_trial(trial: Trial, params: PlantParameters | None = None) -> dict:
    plant = HandPlant(params or PlantParameters(), seed=0)
    with tempfile.TemporaryDirectory() as store:
        fw = Firmware(plant=plant, store_dir=store, seed=0)
        try:
            return _grasp_lift_hold(fw, plant, trial)
        finally:
            fw.shutdown()
            plant.close()


def _rise(s: float) -> float:
    """The arm's minimum-jerk lift, metres, at the fraction `s` of its time."""
    return LIFT_HEIGHT * s ** 3 * (10 - 15 * s + 6 * s * s)


class _LoopGrasp:
    """BH8Grasp-v0's LOOP driven as `--mode loop` drives it: each `cycle` sends one control block
    (fingers LCV 100 at gain 255, or 0 once stalled if `lock_stalled`; the spread held at 0 by
    LoopBaseline's law on LFAP) and reads the feedback, noting the highest finger strain and whether
    the safety envelope would have stopped."""

    def __init__(self, fw: Firmware, spread_gain: float, lock_stalled: bool):
        self.fw = fw
        self.spread_gain = spread_gain
        self.lock_stalled = lock_stalled
        self.interface = interface = grasp_interface()
        self.layout = interface.layout
        for line in (*interface.setup_commands, interface.baud_command):
            fw.transact(line.encode() + b"\r")
        self._spread = self.layout.feedback_fields.index((SPREAD_MOTOR, "LFAP"))
        self._finger_positions = {m: self.layout.feedback_fields.index((m, "LFAP")) for m in FINGER_MOTORS}
        self.stalls = StalledFingers()
        self.stalled = self.stalls.stalled
        self._strains = [i for i, (m, name) in enumerate(self.layout.feedback_fields) if name == "LFS" and m != SPREAD_MOTOR]
        self.spread_position = 0
        self.max_strain = 0
        self.safety_limit = SafetyEnvelope().max_strain

    def enter(self) -> None:
        loop = self.interface.loop_command.encode()
        echo = self.fw.transact(loop + b"\r")
        if echo != loop + b"*":
            raise RuntimeError(f"LOOP answered {echo!r}")

    def cycle(self) -> None:
        values = []
        for motor, name in self.layout.control_fields:
            if motor == SPREAD_MOTOR:
                values.append(int(np.clip(self.spread_gain * -self.spread_position, -127, 127)) if name == "LCV" else LOOP_GAIN)
            else:
                velocity = 0 if self.stalled[motor] else LOOP_CLOSE_VELOCITY
                values.append(velocity if name == "LCV" else LOOP_GAIN)
        self.fw.write(self.interface.encode_action(values))
        self.fw.run_until_idle()
        feedback = self.layout.decode_feedback(self.fw.read())
        self.spread_position = feedback[self._spread]
        if self.lock_stalled:
            self._note_stalls(feedback)
        self.max_strain = max(self.max_strain, *(feedback[i] for i in self._strains))

    def _note_stalls(self, feedback) -> None:
        """A finger that has stalled (`StalledFingers`: the firmware's own rule at the default TSTOP)
        gets LCV 0 from then on, and its worm holds it (§9.3.1)."""
        self.stalls.update(self.fw.time, {m: feedback[i] for m, i in self._finger_positions.items()})

    def run_for(self, seconds: float, wrist=None) -> None:
        """Cycles for `seconds`; `wrist(elapsed)`, if given, is where the arm puts the wrist at the
        start of each cycle (as the env's arm moves once per cycle)."""
        start = self.fw.time
        while self.fw.time - start < seconds - 1e-9:
            if wrist is not None:
                self.fw.plant.set_wrist_pose(wrist(self.fw.time - start), PALM_DOWN)
            self.cycle()


def _grasp_lift_hold(fw: Firmware, plant: HandPlant, trial: Trial) -> dict:
    dt = plant.dt
    loop = _LoopGrasp(fw, trial.spread_gain, trial.lock_stalled) if trial.mode == "loop" else None
    # The hand is initialised high above the table, then the arm brings it over the object.
    if loop is None:
        fw.transact(b"HI\r")
        fw.transact(b"GFSET HOLD 0\r")
    body, height = _object(plant, trial)
    wrist_z = max(height + KNUCKLE_HEIGHT + trial.clearance, MIN_PALM_ABOVE_TABLE) + PALM_TOP
    plant.set_wrist_pose((0.0, 0.0, wrist_z), PALM_DOWN, teleport=True)
    fw.run_for(0.1)  # the object settles
    fingers = {plant._link_index_by_name[f"f{f}_{part}"]: f - 1 for f in (1, 2, 3) for part in ("inner", "outer")}
    outer_links = {plant._link_index_by_name[f"f{f}_outer"] for f in (1, 2, 3)}
    first_contact = [None, None, None]
    breakaway = [None, None, None]  # when each finger's clutch broke away after its first contact
    outer_meets = [None, None, None]  # when, after that, its outer link (driven on alone) met the object
    if loop is None:
        fw.write(b"GC\r")
        start = fw.time
        while not fw.idle:
            if fw.time - start > GC_LIMIT_S:
                fw.write(b"\x03")
                fw.run_until_idle()
                break
            fw.run_for(dt)
            now = fw.time - start
            for finger in 0, 1, 2:
                if first_contact[finger] is not None and breakaway[finger] is None and not plant.clutch_engaged(finger + 1):
                    breakaway[finger] = now
            for contact in p.getContactPoints(bodyA=plant.hand_id, bodyB=body, physicsClientId=plant.client):
                finger = fingers.get(contact[3])
                if finger is not None and first_contact[finger] is None:
                    first_contact[finger] = now
                if finger is not None and breakaway[finger] is not None and outer_meets[finger] is None \
                        and contact[3] in outer_links:
                    outer_meets[finger] = now
        fw.read()
        gc_seconds = fw.time - start
    else:
        loop.enter()
        loop.run_for(LOOP_GRASP_S)
        gc_seconds = LOOP_GRASP_S
    gc_loads = plant.strain_gauges()[:3] - np.array(plant.strain_offsets)
    touching = {fingers[c[3]] for c in p.getContactPoints(bodyA=plant.hand_id, bodyB=body, physicsClientId=plant.client)
                if c[3] in fingers}
    closed = 2 in touching and bool(touching & {0, 1})
    stopped_on_it = len(touching) == 3 and bool(np.all(plant.motor_positions()[:3] < CT_COUNTS - CT_MARGIN))
    if loop is None:
        steps = round(LIFT_SECONDS / dt)
        for k in range(1, steps + 1):
            plant.set_wrist_pose((0.0, 0.0, wrist_z + _rise(k / steps)), PALM_DOWN)
            fw.run_for(dt)
    else:
        loop.run_for(LIFT_SECONDS, lambda t: (0.0, 0.0, wrist_z + _rise(min(t / LIFT_SECONDS, 1.0))))
    lifted_position, lifted_orientation = _relative_pose(plant, body)
    if loop is None:
        for k in range(round(HOLD_SECONDS / dt)):
            if trial.shake:
                x = SHAKE_AMPLITUDE * math.sin(2 * math.pi * SHAKE_HZ * k * dt)
                plant.set_wrist_pose((x, 0.0, wrist_z + LIFT_HEIGHT), PALM_DOWN)
            fw.run_for(dt)
    else:
        shake = SHAKE_AMPLITUDE if trial.shake else 0.0
        loop.run_for(HOLD_SECONDS, lambda t: (shake * math.sin(2 * math.pi * SHAKE_HZ * t), 0.0, wrist_z + LIFT_HEIGHT))
    position, orientation = _relative_pose(plant, body)
    slip = float(np.linalg.norm(position - lifted_position))
    turn = p.getDifferenceQuaternion(lifted_orientation.tolist(), orientation.tolist())
    rotation = math.degrees(2.0 * math.acos(min(1.0, abs(turn[3]))))
    loads = plant.strain_gauges()[:3] - np.array(plant.strain_offsets)
    kept = slip < KEPT_DISTANCE and float(plant.object_pose(body)[0][2]) > LIFT_HEIGHT / 2
    squeezed = bool(loads.sum() >= 0.7 * gc_loads.sum())
    after_contact = None
    if loop is None and stopped_on_it and None not in first_contact:
        after_contact = gc_seconds - max(m if m is not None else (b if b is not None else f)
                                         for f, b, m in zip(first_contact, breakaway, outer_meets))
    over_limit = loop is not None and loop.max_strain > loop.safety_limit
    return dict(closed=closed, all_three=len(touching) == 3, kept=kept, squeezed=squeezed, slip_mm=slip * 1000.0, rotation_deg=rotation, gc_s=gc_seconds,
                after_contact_s=after_contact, over_limit=over_limit,
                gc_loads=gc_loads.tolist(), loads=loads.tolist())


def summarize(shape: str, results: list[dict], mode: str = "gc") -> str:
    closed = [r for r in results if r["closed"]]
    kept = [r for r in closed if r["kept"]]
    slip = np.array([r["slip_mm"] for r in kept]) if kept else np.array([np.nan])
    rotation = np.array([r["rotation_deg"] for r in kept]) if kept else np.array([np.nan])
    kept_share = 100.0 * len(kept) / len(closed) if closed else float("nan")
    squeezed = sum(r["squeezed"] for r in kept)
    all_three = sum(r["all_three"] for r in results)
    line = (f"{shape:9s} {len(closed):3d}/{len(results):<3d} {all_three:3d}    {len(kept):3d} ({kept_share:5.1f} %)  "
            f"{squeezed:3d}      {np.median(slip):6.2f} {np.max(slip):6.2f}   {np.median(rotation):5.2f} {np.max(rotation):6.2f}   ")
    if mode == "loop":
        return line + f"{sum(r['over_limit'] for r in results):3d}"
    after = np.array([r["after_contact_s"] for r in results if r["after_contact_s"] is not None] or [np.nan])
    prompt = 100.0 * np.mean(after <= TSTOP_S + 0.2)
    return line + f"{np.median(after):5.2f} {np.max(after):5.2f} {prompt:5.0f} % of {np.count_nonzero(~np.isnan(after))}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mode", choices=MODES, default="gc",
                        help="gc: GC with HOLD 0; loop: LOOP at LCV 100, gain 255 throughout (default: %(default)s)")
    parser.add_argument("--shapes", nargs="+", choices=SHAPES, default=list(SHAPES), help="default: all four")
    parser.add_argument("--placements", type=int, default=15, help="placements per shape and size (default: %(default)s)")
    parser.add_argument("--spread-gain", type=float, default=SPREAD_GAIN,
                        help="--mode loop: LCV bytes per count of the spread's error (default: %(default)s)")
    parser.add_argument("--drive-stalled", action="store_true",
                        help="--mode loop: keep driving a finger at LCV 100 after it has stalled (default: LCV 0 then)")
    parser.add_argument("--shake", action="store_true", help="shake the lifted hand ±1 cm at 2 Hz during the hold")
    parser.add_argument("--seed", type=int, default=0, help="seed of the placements, masses and frictions (default: %(default)s)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default: %(default)s)")
    parser.add_argument("--verbose", action="store_true", help="print every trial")
    args = parser.parse_args()
    if not (math.isfinite(args.spread_gain) and args.spread_gain >= 0.0):
        parser.error(f"--spread-gain must be a finite number >= 0, got {args.spread_gain!r}")
    todo = trials(args.shapes, args.placements, args.shake, args.seed, args.mode, args.spread_gain, not args.drive_stalled)
    started = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(run_trial, todo, chunksize=4))
    if args.verbose:
        for trial, result in zip(todo, results):
            print(trial, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in result.items()})
    grasp = "GC" if args.mode == "gc" else (
        f"LOOP at LCV {LOOP_CLOSE_VELOCITY}, gain {LOOP_GAIN} ({'driven on' if args.drive_stalled else 'LCV 0'} once stalled), "
        f"spread gain {args.spread_gain:g}")
    print(f"{grasp}; {'hold' if not args.shake else 'shaken hold'} {HOLD_SECONDS:g} s after a {LIFT_HEIGHT * 100:g} cm lift; "
          f"{args.placements} placements x {len(SIZES)} sizes per shape, seed {args.seed}")
    last = ("GC after last contact s: median max, within TSTOP+0.2 of those stopped on it" if args.mode == "gc"
            else f"strain over {SafetyEnvelope().max_strain}")
    print(f"shape     closed  all 3  kept (of closed)  squeezed  slip mm: median max  rot. deg: median max  {last}")
    for shape in args.shapes:
        print(summarize(shape, [r for t, r in zip(todo, results) if t.shape == shape], args.mode))
    closed = [r for r in results if r["closed"]]
    kept = [r for r in closed if r["kept"]]
    print(f"all       {len(closed)}/{len(results)} closed, {len(kept)} kept ({100.0 * len(kept) / max(len(closed), 1):.1f} %); "
          f"{time.perf_counter() - started:.0f} s wall")


if __name__ == "__main__":
    main()
