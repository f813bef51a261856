"""The simulated BH8-262: a PyBullet world with the hand on a movable wrist, its drive train and sensors.

`HandPlant` (`hand`) is the one facade the firmware and the environments use; its parts are the
hardware's: `drive_train` (motors, worms, the finger coupling, the spread), `clutch` (the
TorqueSwitch, and the motor torques and heat of each step), `sensors` (encoders, strain gauges,
temperature) and `world` (table, wrist, bodies, contacts, saved states); `parameters` holds
`PlantParameters`, `joints` the joint indices, units and the plant's own state.

This is the hardware below the HCTL-1100 chips (docs/architecture.md, Contract 1): four motors
(1-3 fingers, 4 spread; positive motion closes), worm gears, the TorqueSwitch clutch, strain gauges
and heat. Sources: manual §9.3 (TorqueSwitch, spread), §9.4 (strain gauges), §9.5 Equations 4-5
(ratios), Table 7 (motors), §2 (temperature), App. A (speeds, mass); SPEC.md §1 and §8.

Drive-train model (one finger; docs/modelling.md tells the why and the numbers):
* The motor is a velocity source with a torque limit: `set_drive(m, counts_per_s, fraction)`.
* Worm drives: each finger joint has a window it cannot leave, set as PyBullet joint limits. An
  unpowered joint's window is where it stopped; a driven joint's back edge follows the furthest
  position its drive reached (`worm_slack` behind, moved lazily), its front edge is its stop, or the
  palm (`hand_urdf.palm_stop`: a closed fingertip rests on the palm face). A load helping the motion
  cannot make it run faster than its motor turns (`overrun_brake_torque`). The encoder of a locked
  finger reads its hold position (the worm holds the motor shaft).
* Clutch engaged: the inner joint turns at M/125 degrees and the outer joint (relative to the inner
  link) at M/375, so the outer link's angle to the palm is always M/93.75 (SPEC §1): the motor
  position reported is 93.75 x that angle. Both joints are driven; their targets are corrected
  towards the exact 3:1 relation every step (`coupling_rate`) and neither leads the other by more
  than three worm slacks, so a blocked link stops the whole finger (a joint its partner holds back
  is held there by its window's front edge, not by a zero velocity target alone); the motor's torque
  budget is shared: inner torque + outer torque / 3 <= fraction x peak x 125 x efficiency.
* TorqueSwitch: while closing, the torque the clutch passes to the inner link (its share of the
  motor torque plus the rotor's impact when the link is stopped suddenly, unless the outer link took
  the blow, App. B A1) above `breakaway_base_torque + breakaway_preload_slope x preload` disengages
  the clutch: the inner link locks where it is and the motor drives the outer link alone at
  M/93.75 degrees. Opening re-engages it at the breakaway position. The preload is the peak clutch
  torque of the last drive against the open stop, up to `preload_limit`; backing off the stop
  (`back_off_stop`, HI's IOFF) unwinds part of it; a breakaway resets it to zero.
* A finger that locks while its drive squeezes an object keeps pressing with the latched torque
  (elastic wind-up, at most `lock_elastic_travel` further closed, never opening), so a grasp
  survives HOLD 0 (§9.3.1, FAQ A1).
* The spread is back-drivable: unpowered it has only `spread_friction_torque`; F1 and F2 spread
  symmetrically (a gear constraint couples them).
* Contact: friction anchors on the hand's links (no creep of a held object), split impulse off.
* `set_parameters` applies new PlantParameters to a live plant (domain randomisation).
* Strain gauge = offset + gain x the torque the outer joint transmits, 8 bits. Heat: electronics +
  sum (torque/Km)^2.
"""
from bh8_gym.plant.hand import HandPlant
from bh8_gym.plant.joints import (
    FINGER_JOINTS,
    INNER_COUNTS_PER_RAD,
    INNER_GEAR_RATIO,
    INNER_INDEX,
    NUM_JOINTS,
    OUTER_ABS_COUNTS_PER_RAD,
    OUTER_ABS_GEAR_RATIO,
    OUTER_INDEX,
    OUTER_REL_GEAR_RATIO,
    SPREAD_COUNTS_PER_RAD,
    SPREAD_GEAR_RATIO,
    SPREAD_INDEX,
    WORM_JOINTS,
)
from bh8_gym.plant.parameters import DisplayUnavailableError, PlantError, PlantParameters

__all__ = [
    "DisplayUnavailableError",
    "FINGER_JOINTS",
    "HandPlant",
    "INNER_COUNTS_PER_RAD",
    "INNER_GEAR_RATIO",
    "INNER_INDEX",
    "NUM_JOINTS",
    "OUTER_ABS_COUNTS_PER_RAD",
    "OUTER_ABS_GEAR_RATIO",
    "OUTER_INDEX",
    "OUTER_REL_GEAR_RATIO",
    "PlantError",
    "PlantParameters",
    "SPREAD_COUNTS_PER_RAD",
    "SPREAD_GEAR_RATIO",
    "SPREAD_INDEX",
    "WORM_JOINTS",
]
