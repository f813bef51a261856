"""The plant's physical constants (`PlantParameters`, the domain-randomisation knobs) and its errors.

Every constant the manual does not give is a field here with a comment naming its source.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

from bh8_gym.hand_urdf import FINGER_WIDTH
from bh8_gym.settings import dataclass_from, matches_annotation

from bh8_gym.plant.joints import _DEG


class PlantError(ValueError):
    """A bad argument to the plant's API (names the offending value)."""


class DisplayUnavailableError(RuntimeError):
    """gui=True (render_mode="human", `bh8 serve --gui`) on a machine without a display."""


@dataclass
class PlantParameters:
    """Physical constants of the simulated hand and world; the domain-randomisation knobs.

    Values the documents give cite them; the others are our estimates, each with its reason.
    """

    # Physics.
    time_step: float = 0.002  # s; 500 Hz keeps contact stable with the light finger links (<= 2 ms)
    solver_iterations: int = 50  # PyBullet's default
    # The solver stops early once an iteration changes the impulses by less than this (PyBullet's
    # solverResidualThreshold, default 1e-7): 8 % of the grasp env's time, the same holds in bench_hold.
    solver_residual_threshold: float = 1e-4
    gravity: float = 9.81  # m/s^2

    # Motors (Table 7) and gears.
    motor_peak_torque: float = 0.05  # N·m: Table 7, 5 N·cm
    motor_constant: float = 0.0083  # N·m/sqrt(W): Table 7, 0.83 N·cm/sqrt(W)
    motor_no_load_speed: float = 54_000.0  # counts/s (150 rev/s): above App. A's need (MCV 100 = 24,400/s)
    finger_drive_efficiency: float = 0.4  # worm + cable drive (self-locking worms run below 50 %)
    spread_drive_efficiency: float = 0.7  # spur gears of the back-drivable spread
    worm_lock_torque: float = 40.0  # N·m at a joint: a self-locking worm holds any realistic load
    spread_friction_torque: float = 0.03  # N·m per spread joint, unpowered (back-drivable, §9.3.2)
    coupling_rate: float = 250.0  # 1/s: how fast joint targets pull the 3:1 relation back (stiff gearing)
    # Share of the finger drive's torque the outer joint keeps when the inner one takes the load
    # (stalled, engaged; the inner keeps 5 %): a rigid gear train splits the load by contact geometry,
    # which rigid PyBullet contacts do not resolve. 6.5 % keeps a fingertip pressing (§5.5 HSG) after the
    # inner link touched first, yet leaves the inner enough torque to break away (§9.3.1).
    coupled_torque_floor: float = 0.065
    lock_position_gain: float = 0.2  # PyBullet position gain that holds the spread at a stop it is driven into
    # A worm is not back-drivable: a load cannot turn a finger joint against its drive, nor turn an
    # unpowered one at all. Each finger joint has a window it may not leave (PyBullet joint limits, hard
    # as the worm's teeth): a driven joint cannot go back more than this (to twice this, as the window
    # is moved lazily) behind the furthest position its drive has reached; an unpowered one stays where
    # it stopped. The slack is the drive train's compliance (gear backlash, cable and link elasticity),
    # and it keeps the limits out of the solver until a load pushes against the worm: with none, the
    # grasp env steps 14 % slower (callgrind).
    worm_slack: float = 0.05 * _DEG
    # Nor can a load helping the motion make a finger joint run faster than the motor turns it. A joint
    # within this fraction of its target speed (or faster) is braked at its target speed unless its
    # motor has to push at its limit.
    overrun_tolerance: float = 0.02
    # N·m at a joint available to brake an overrunning joint. Physically the worm's lock torque, but a
    # PyBullet motor's limit is symmetric: the brake also pushes forward until the next step notices a
    # stop or an object. The full motor torque at the inner joint (0.05 x 125 x 0.4) is far above the
    # aiding loads (finger weight about 0.05 N·m) and no more than the motor itself could push.
    overrun_brake_torque: float = 0.3
    # Squeeze kept by a locked finger (§9.3.1, FAQ A1: the grasp stays with the motor current removed).
    # The finger links and cable are elastic: a drive stalled against a load winds them up, and the
    # self-locking worm keeps that load when it locks. Our estimate of the elastic travel: about 1° at
    # a joint under full motor torque (aluminium links, steel cable).
    lock_elastic_travel: float = 1.0 * _DEG  # rad of closing travel allowed beyond the hold position
    # A drive pushing at this fraction of its torque limit or more is stalled against a load (not just
    # moving the link), so its torque is latched when the finger locks.
    squeeze_latch_fraction: float = 0.5

    # TorqueSwitch (SPEC §8: our choice, documented in the module docstring).
    breakaway_base_torque: float = 0.25  # N·m at the inner joint with no preload (10 % of full motor torque)
    breakaway_preload_slope: float = 1.0  # §9.3.1: loosening torque equals tightening torque (screw)
    # N·m per rad/s of inner-link speed lost at impact: the rotor's inertia reflected through 125:1
    # against the drive's compliance (a 1e-6 kg·m² rotor, 125², 50 N·m/rad: about 0.9). With
    # preload_limit it puts the breakaway of a C against a blocked inner link, after a default HI, at
    # MCV 37.5: from MCV 40 up it breaks away, at 35 it does not (manual §8 troubleshooting: "The close
    # velocity is too slow. Increase the close velocity greater than or equal to 40").
    rotor_impact_gain: float = 1.0
    impact_memory_time: float = 0.5  # s: the decay of the inner link's remembered speed, what an impact loses
    # N·m on the outer joint when the finger stops: from none to this much, less and less of the
    # rotor's impact reaches the clutch (App. B A1: a fingertip that makes first contact stalls the
    # finger; only an inner link that does breaks away). A finger stopped at its inner link carries
    # about 0.01 N·m there, one stopped at its fingertip about 0.85 (measured at MCV 100).
    tip_impact_load: float = 0.3
    stop_tolerance: float = 0.05 * _DEG  # rad: a joint this close to its limit is against its stop
    initial_preload: float = 3.47  # N·m: the hand starts as a default HI leaves it (0.9 x preload_limit)
    # §5.3.4 IOFF: "Larger values result in less compression of the Belleville washer ... its true range
    # of useful values is from 0 to approximately 500". Backing off the open stop (HI's move to 0 closes
    # IOFF counts) unwinds the preload linearly over this many counts (`back_off_stop`).
    preload_release_counts: float = 500.0
    # N·m: the most the Belleville washers take. Their force is nearly flat over their working travel
    # (the reason for Belleville springs), so slamming the finger open harder than HI does (IVEL 300)
    # preloads no more.
    preload_limit: float = 3.86

    # Strain gauges (§9.4, SPEC §1).
    strain_gain: float = 100.0  # counts per N·m about the outer joint: Figure 28 plots ΔSG -100..100 over -1..1 N·m
    strain_offsets: tuple[int, int, int] | None = None  # no-load values; None: seeded in 100..140

    # Thermal (§2: the hand runs at 40-60 °C).
    ambient_temperature: float = 22.0  # °C, a lab
    electronics_power: float = 8.0  # W dissipated by the CPU and power boards at idle (estimate)
    thermal_resistance: float = 2.9  # K/W to ambient: idle steady state 22 + 8 x 2.9 = 45 °C
    heat_capacity: float = 1000.0  # J/K: 1.18 kg of mostly aluminium (900 J/kg/K)
    initial_temperature: float | None = None  # °C; None: the idle steady state

    # Contact.
    finger_friction: float = 0.8  # finger links on typical objects (aluminium/rubber-ish pads)
    palm_friction: float = 0.6
    table_friction: float = 0.6
    object_friction: float = 0.7  # default of an object placed by hand (bh8_gym.objects.add_object)
    # Static friction that holds: PyBullet's friction anchors keep a sticking contact's anchor point, so
    # a held object does not creep through solver error (without them a worm-locked grasp slipped 9 mm
    # and turned 33° in 5 s).
    friction_anchors: bool = True
    # m: radius of the contact patch a finger link's rubber pad makes on an object (0: point contacts). A
    # point contact (PyBullet's) resists no turn about its normal, so an object pinched between two
    # fingertips can pivot about the line through the contacts under its own weight (bench_hold.py --mode
    # loop). A pad pressed flat resists it: a uniform circular patch of radius a carries up to (2/3)·mu·N·a.
    # Hertz's estimate for a rubber pad (E about 3 MPa) pressed with 10-30 N on a 4-8 cm object: a = 3-6 mm.
    # The links get PyBullet's torsional friction (2/3)·a·finger_friction, which PyBullet multiplies by the
    # other body's friction: (2/3)·a·mu for the pair. Off: at 4 mm fingertips pressed on the table at full
    # LOOP torque chatter (tests/test_table_contact.py; at 2 mm less, still over its limit), and the pinch's
    # creep in bench_hold is the solver's early stop, not too little torsional friction (docs/modelling.md).
    finger_pad_radius: float = 0.0
    link_mass_scale: float = 1.0  # scales every hand link's mass (randomisation)

    # World.
    table: bool = True  # a table whose top is the plane z = 0
    wrist_position: tuple[float, float, float] = (0.0, 0.0, 0.30)  # m: initial arm flange
    wrist_orientation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)  # palm down (xyzw)
    wrist_max_force: float = 2000.0  # N: the arm is much stronger than the hand

    @classmethod
    def from_overrides(cls, overrides) -> "PlantParameters":
        """The defaults with some fields replaced: `overrides` is a PlantParameters (returned as it
        is) or a mapping of field names to values, as a TOML config or JSON env kwargs give them."""
        params = dataclass_from(cls, overrides, "plant parameters", error=PlantError)
        params.validate()
        return params

    def validate(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not matches_annotation(item.type, value):
                raise PlantError(f"{item.name} must be {item.type}, got {value!r}")
        if not 0.0 < self.time_step <= 0.002:
            raise PlantError(f"time_step must be in (0, 0.002] s, got {self.time_step!r}")
        if self.solver_iterations < 1:
            raise PlantError(f"solver_iterations must be at least 1, got {self.solver_iterations!r}")
        if not self.solver_residual_threshold >= 0.0:
            raise PlantError(f"solver_residual_threshold must be >= 0, got {self.solver_residual_threshold!r}")
        if not self.preload_release_counts > 0.0:
            raise PlantError(f"preload_release_counts must be > 0, got {self.preload_release_counts!r}")
        if not 0.0 <= self.finger_pad_radius <= FINGER_WIDTH / 2:  # a patch no wider than the finger
            raise PlantError(f"finger_pad_radius must be 0 to {FINGER_WIDTH / 2:g} m (half a finger's width), "
                             f"got {self.finger_pad_radius!r}")
        if not self.worm_slack >= 0.0:
            raise PlantError(f"worm_slack must be >= 0, got {self.worm_slack!r}")
