"""The TorqueSwitch clutch of each finger (manual §9.3), and what a step cost the motors.

`Clutch` is one part of `HandPlant` (a mixin on the plant's `params` and `_state`). After each
physics step `_update_after_step` reads the joints: a closing finger whose inner link is held back
hard enough breaks away (the inner link locks, the motor drives the outer link alone), opening
re-engages it, a drive against the open stop preloads it (`back_off_stop` unwinds part of that);
the same pass gives each motor's torque, the heat they make and the simulated time. The model:
the `bh8_gym.plant` docstring, docs/modelling.md.
"""
from __future__ import annotations

import math

import pybullet as p

from bh8_gym.plant.joints import (
    FINGER_JOINTS,
    INNER_COUNTS_PER_RAD,
    INNER_INDEX,
    OUTER_ABS_COUNTS_PER_RAD,
    OUTER_INDEX,
    SPREAD_INDEX,
    _PlantState,
)
from bh8_gym.plant.parameters import PlantError, PlantParameters


class Clutch:
    """The fingers' TorqueSwitch clutches in `HandPlant` (module docstring)."""

    params: PlantParameters
    _state: _PlantState
    dt: float

    def _update_after_step(self) -> None:
        """Clutch events, preload, motor torques, heat and time, from the joint states just read."""
        prm, state = self.params, self._state
        q, w, tau = state.positions, state.velocities, state.torques
        decay = self._impact_decay
        heat = 0.0
        inner_open, inner_closed, outer_closed = self._inner_open, self._inner_closed, self._outer_closed
        impact_gain, tip_blow = prm.rotor_impact_gain, prm.tip_impact_load
        drive_on, drive_velocity, drive_fraction = state.drive_on, state.drive_velocity, state.drive_fraction
        closing_peaks, opening_peaks, motor_torques = state.closing_peak, state.opening_peak, state.motor_torques
        for f, i2, i3 in FINGER_JOINTS:
            inner_speed = w[i2]
            previous_closing, previous_opening = closing_peaks[f], opening_peaks[f]
            # Decaying peaks of the inner link's closing and opening speeds (rotor impact memory).
            closing_peak, opening_peak = previous_closing * decay, previous_opening * decay
            if inner_speed > closing_peak:
                closing_peak = inner_speed
            elif -inner_speed > opening_peak:
                opening_peak = -inner_speed
            velocity = drive_velocity[f]
            fraction = drive_fraction[f]
            if drive_on[f] and velocity < 0.0:
                # A rotor driven open keeps no closing speed: the next close's impacts lose only what
                # that close reached (a remembered faster close made its start look held back).
                closing_peak = 0.0
            elif drive_on[f] and velocity > 0.0:
                # Nor does a rotor driven closed keep an opening speed: the next open's blow on the
                # stop preloads with what that open reached, not with an earlier, faster open.
                opening_peak = 0.0
            closing_peaks[f], opening_peaks[f] = closing_peak, opening_peak
            if not (drive_on[f] and velocity != 0.0 and fraction > 0.0):
                motor_torques[f] = 0.0
                continue
            if state.engaged[f]:
                capacity = fraction * self._finger_capacity
                if velocity > 0.0 and q[i3] < outer_closed:
                    # Closing: the torque the clutch passes to the inner link when something holds that
                    # link back (not while it merely accelerates), the outer link's load excluded.
                    commanded = velocity / INNER_COUNTS_PER_RAD
                    if q[i2] >= inner_closed:
                        clutch = capacity
                    elif inner_speed < 0.5 * commanded and inner_speed <= previous_closing + 0.02 * commanded:
                        outer_load = tau[i3]
                        clutch = capacity - outer_load / 3.0 if outer_load > 0.0 else capacity
                        if tau[i2] < clutch:
                            clutch = tau[i2]
                    else:
                        clutch = 0.0
                    if clutch > 0.0:
                        lost = previous_closing - (inner_speed if inner_speed > 0.0 else 0.0)
                        if lost > commanded:  # the worm: the link ran no faster than the motor turns
                            lost = commanded
                        # App. B A1: a fingertip making first contact stalls the finger (no breakaway):
                        # a loaded outer joint took the blow, and the rotor's impact went into its worm.
                        blow = 1.0 - state.outer_loads[f] / tip_blow if state.outer_loads[f] > 0.0 else 1.0
                        if lost > 0.0 and blow > 0.0:
                            clutch += impact_gain * lost * blow * (clutch / capacity if clutch < capacity else 1.0)
                        if clutch > prm.breakaway_base_torque + prm.breakaway_preload_slope * state.preload[f] \
                                and (q[i2] >= inner_closed or self._finger_touches(f)):
                            self._break_away(f)
                elif velocity < 0.0 and q[i2] <= inner_open:
                    # Driven against the open stop: the clutch is tightened with the motor's torque plus
                    # the rotor's impact (§9.3.1; slamming open harder preloads more, manual §8).
                    lost = previous_opening - (-inner_speed if inner_speed < 0.0 else 0.0)
                    if lost > -velocity / INNER_COUNTS_PER_RAD:  # the worm: no faster than the motor turns
                        lost = -velocity / INNER_COUNTS_PER_RAD
                    preload = capacity + (impact_gain * lost if lost > 0.0 else 0.0)
                    if preload > prm.preload_limit:
                        preload = prm.preload_limit
                    if preload > state.preload[f]:
                        state.preload[f] = preload
            elif velocity < 0.0 and q[i3] <= q[i2] / 3.0:
                # Opening: the outer link is back at the engaged relation (M at the breakaway position).
                state.engaged[f] = True
            limit = fraction * prm.motor_peak_torque
            if state.at_stop[f]:
                torque = limit if velocity > 0.0 else -limit  # stalled against the stop: full push
            elif state.engaged[f]:
                torque = (tau[i2] + tau[i3] / 3.0) * self._inner_torque_scale
            else:
                torque = tau[i3] * self._outer_torque_scale
            torque = limit if torque > limit else (-limit if torque < -limit else torque)
            motor_torques[f] = torque
            heat += torque * torque
        if state.drive_on[3]:
            limit = state.drive_fraction[3] * prm.motor_peak_torque
            if state.held[SPREAD_INDEX[0]]:  # stalled against a stop (the stop, not the motor, holds the joint)
                torque = limit if state.drive_velocity[3] > 0.0 else -limit
            else:
                torque = tau[SPREAD_INDEX[0]] * self._spread_torque_scale
                torque = limit if torque > limit else (-limit if torque < -limit else torque)
            heat += torque * torque
        else:
            torque = 0.0
        state.motor_torques[3] = torque
        km = prm.motor_constant
        power = prm.electronics_power + heat / (km * km)
        loss = (state.temperature - prm.ambient_temperature) / prm.thermal_resistance
        state.temperature += self.dt * (power - loss) / prm.heat_capacity
        state.time += self.dt

    def _finger_touches(self, f: int) -> bool:
        """Whether finger f's links touch anything (an object, the table, another finger) after this
        step: only something the finger meets holds its inner link back (§9.3.1: "If the inner finger
        link, while closing, contacts a target object ..."; one met by the outer link near its joint
        holds the inner link too). A finger its own drive cannot carry (a few % of duty at a profile's
        start, its weight on it) slows with its rotor, and no impact passes the clutch."""
        hand, client = self.hand_id, self._client
        return any(p.getContactPoints(bodyA=hand, linkIndexA=link, physicsClientId=client) for link in self._finger_links[f])

    def _break_away(self, f: int) -> None:
        state = self._state
        state.engaged[f] = False
        state.breakaway_counts[f] = self._finger_counts(f)
        state.preload[f] = 0.0  # manual §8: the clutch needs a full open to be preloaded again

    def back_off_stop(self, finger: int, counts: float) -> None:
        """Finger 1-3 is about to move `counts` closed from its open stop after being driven against it
        (HI's move to 0 closes IOFF counts): that unwinds part of the clutch's preload (§5.3.4 IOFF:
        "Larger values result in less compression of the Belleville washer", no effect beyond about
        500 counts; `preload_release_counts`)."""
        f, release = self._check_finger(finger), self.params.preload_release_counts
        counts = float(counts)
        if not (math.isfinite(counts) and counts >= 0.0):
            raise PlantError(f"counts must be a finite number >= 0, got {counts!r}")
        self._state.preload[f] *= 1.0 - counts / release if counts < release else 0.0

    def _finger_counts(self, f: int) -> float:
        q = self._state.positions
        return (q[INNER_INDEX[f]] + q[OUTER_INDEX[f]]) * OUTER_ABS_COUNTS_PER_RAD

    def clutch_engaged(self, finger: int) -> bool:
        """True while finger 1-3's TorqueSwitch couples both joints to the motor."""
        return self._state.engaged[self._check_finger(finger)]

    def breakaway_position(self, finger: int) -> float | None:
        """Motor counts at finger 1-3's last breakaway, or None if it never broke away."""
        return self._state.breakaway_counts[self._check_finger(finger)]

    def clutch_preload(self, finger: int) -> float:
        """The clutch preload of finger 1-3 (N·m at the inner joint)."""
        return self._state.preload[self._check_finger(finger)]

    def breakaway_threshold(self, finger: int) -> float:
        """Inner-joint torque (N·m) above which finger 1-3's clutch breaks away now."""
        prm = self.params
        return prm.breakaway_base_torque + prm.breakaway_preload_slope * self._state.preload[self._check_finger(finger)]

    def _check_finger(self, finger) -> int:
        if finger not in (1, 2, 3) or isinstance(finger, bool):
            raise PlantError(f"finger must be 1, 2 or 3, got {finger!r}")
        return int(finger) - 1
