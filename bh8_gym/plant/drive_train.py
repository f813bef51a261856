"""The drive train of the simulated hand: four motors, the worms and the finger coupling.

`DriveTrain` is one part of `HandPlant` (a mixin: it works on the plant's `params` and `_state`):
the drives the firmware sets (`set_drive`, `set_drives`, `step_with_drives`) and, once per step,
the joint targets, force limits and worm windows they give (`_command_joints`): each finger's
worms, the 3:1 coupling of its joints while the clutch is engaged, the palm as a stop, and the
back-drivable spread. The model and its numbers: the `bh8_gym.plant` docstring, docs/modelling.md.
"""
from __future__ import annotations

import math
from bisect import bisect_left

from bh8_gym.plant.joints import (
    _IDLE_FORCE,
    _PALM_TABLE_STEP,
    _THIRD,
    FINGER_JOINTS,
    INNER_COUNTS_PER_RAD,
    OUTER_ABS_COUNTS_PER_RAD,
    SPREAD_COUNTS_PER_RAD,
    SPREAD_INDEX,
    _PlantState,
)
from bh8_gym.plant.parameters import PlantError, PlantParameters
from bh8_gym.protocol import MOTORS


class DriveTrain:
    """Motors, worms and joint commands of `HandPlant` (module docstring)."""

    params: PlantParameters
    _state: _PlantState
    dt: float

    # ---------------------------------------------------------------- drives
    def _check_motor(self, motor) -> int:
        if motor not in MOTORS or isinstance(motor, bool):
            raise PlantError(f"motor must be 1, 2, 3 or 4, got {motor!r}")
        return int(motor)

    def set_drive(self, motor: int, velocity: float, torque_fraction: float) -> None:
        """Power `motor`: drive towards `velocity` counts/s (+ closes) with at most torque_fraction x peak."""
        index = self._check_motor(motor) - 1
        velocity, torque_fraction = float(velocity), float(torque_fraction)
        if not math.isfinite(velocity):
            raise PlantError(f"velocity must be finite, got {velocity!r}")
        if not 0.0 <= torque_fraction <= 1.0:
            raise PlantError(f"torque_fraction must be in [0, 1], got {torque_fraction!r}")
        limit = self.params.motor_no_load_speed
        state = self._state
        state.drive_velocity[index] = min(max(velocity, -limit), limit)
        state.drive_fraction[index] = torque_fraction
        state.drive_on[index] = True

    def set_drive_off(self, motor: int) -> None:
        """Unpower `motor`: finger worm drives self-lock; the spread is back-drivable."""
        index = self._check_motor(motor) - 1
        self._state.drive_on[index] = False
        self._state.drive_velocity[index] = 0.0
        self._state.drive_fraction[index] = 0.0

    def set_drives(self, velocities, torque_fractions) -> None:
        """All four motors at once. A NaN torque fraction turns that motor off."""
        if len(velocities) != 4 or len(torque_fractions) != 4:
            raise PlantError(f"set_drives needs 4 velocities and 4 torque fractions, got {velocities!r}, {torque_fractions!r}")
        for index in 0, 1, 2, 3:
            velocity, fraction = velocities[index], torque_fractions[index]
            if fraction == fraction and (not 0.0 <= fraction <= 1.0 or not math.isfinite(velocity)):
                raise PlantError(f"motor {index + 1}: velocity {velocity!r} must be finite and torque fraction {fraction!r} in [0, 1]")
        fractions = [float(fraction) for fraction in torque_fractions]
        # the velocity of a motor turned off is not looked at
        self._store_drives([float(v) if f == f else 0.0 for v, f in zip(velocities, fractions)], fractions)

    def step_with_drives(self, velocities: list[float], torque_fractions: list[float]) -> tuple[list[float], list[float]]:
        """The firmware's per-physics-step path: `set_drives` without its checks (the HCTL emulation
        gives finite floats, fractions in [0, 1] or NaN for off), `step`, then `motor_state_lists()`."""
        self._store_drives(velocities, torque_fractions)
        self.step()
        return self.motor_state_lists()

    def _store_drives(self, velocities: list[float], torque_fractions: list[float]) -> None:
        state, limit = self._state, self._speed_limit
        drive_on, drive_velocity, drive_fraction = state.drive_on, state.drive_velocity, state.drive_fraction
        for index in 0, 1, 2, 3:
            fraction = torque_fractions[index]
            if fraction != fraction:  # NaN: off
                drive_on[index] = False
                drive_velocity[index] = drive_fraction[index] = 0.0
            else:
                velocity = velocities[index]
                drive_velocity[index] = limit if velocity > limit else (-limit if velocity < -limit else velocity)
                drive_fraction[index] = fraction
                drive_on[index] = True

    # ---------------------------------------------------------------- worms and joint commands
    def _hold(self, joint: int, latch: float = 0.0) -> None:
        """Lock `joint` (worm self-locking) where it is now, if it is not held already.

        A joint locked with a `latch` torque (its drive was pushing a load closing) keeps pressing with
        it (the elastic wind-up of link and cable), at most `lock_elastic_travel` beyond the hold
        position; it never opens more than the worm's slack below it.
        """
        state, prm = self._state, self.params
        if state.held[joint]:
            return
        state.held[joint] = True
        position = state.positions[joint]
        # Within the joint's range: a link bouncing past a stop (PyBullet's soft limit) is held at it.
        low, high = self._joint_low[joint], self._joint_high[joint]
        position = low if position < low else (high if position > high else position)
        state.hold_positions[joint] = state.target_positions[joint] = position
        state.latched_torque[joint] = latch
        state.position_gains[joint] = 0.0
        # No slack: a limit acts only once a joint is at it, and a light link under a sudden load
        # would cross a slack in one step.
        above = position + prm.lock_elastic_travel if latch > 0.0 else position
        state.window_low[joint] = position
        state.window_high[joint] = above if above < high else high
        if latch > 0.0:
            state.target_velocities[joint], state.forces[joint] = prm.lock_elastic_travel / self.dt, latch
        else:
            state.target_velocities[joint], state.forces[joint] = 0.0, _IDLE_FORCE

    def _squeeze(self, f: int, load: float) -> bool:
        """True if finger f's drive was pushing `load` (N·m, reflected to its joint) closing at its limit."""
        capacity = self._state.drive_capacity[f]
        return capacity > 0.0 and load >= self.params.squeeze_latch_fraction * capacity

    def _drive(self, joint: int, target: float, force: float) -> None:
        state = self._state
        state.held[joint] = False
        state.target_velocities[joint] = target
        state.forces[joint] = force
        state.position_gains[joint] = 0.0

    def _drive_worm(self, joint: int, target: float, force: float, sign: float, high: float | None = None,
                    low: float | None = None) -> None:
        """Drive a finger joint through its worm at `target` rad/s (`sign`: + closes) with at most `force`.

        The worm lets it move only in the drive's direction: its window's back edge follows the
        furthest position reached (lazily, within two `worm_slack`), its front edge is the joint's stop.
        A load helping the motion cannot make it run faster than `target` (the brake), and the motor's
        speed is capped at what ends the step at the stop (PyBullet enforces a limit only once the joint
        is at it, so a fast joint would otherwise overshoot it). `high`, `low`: a closing or opening stop
        short of the joint's own (the palm, for an outer link; a coupled partner held back).
        """
        state = self._state
        state.held[joint] = False
        position = state.positions[joint]
        if high is None:
            high = self._joint_high[joint]
        if low is None:
            low = self._joint_low[joint]
        forward = sign * target
        brake = self._brake_torque
        # (a joint told to wait, forward 0, is braked too: gravity must not turn it either way)
        if forward >= 0.0 and brake > force and sign * state.torques[joint] < force \
                and sign * state.velocities[joint] >= forward * self._overrun_speed_fraction:
            force = brake
        # The back edge follows the joint only up to the front edge: a joint pushed past its front edge
        # (a limit gives a little under load) is held there, not followed on step by step.
        window_low, window_high, slack = state.window_low, state.window_high, self._slack
        if sign > 0.0:
            back = position - slack
            if back - window_low[joint] > slack or window_high[joint] != high:
                if back > high:
                    back = high
                if back < window_low[joint]:
                    back = window_low[joint]  # the back edge never moves back while closing
                back = back if back > low else low
                # (where a stop short of the joint's own, the palm, and the worm's back edge cross, the
                # worm holds: the inner link, stopped by the palm at the outer link's angle, cannot
                # wind the outer link back along the palm)
                window_low[joint], window_high[joint] = back, (high if high > back else back)
            reach = (high - position) / self.dt if position < high else 0.0
            target = target if target < reach else reach
        else:
            back = position + slack
            if window_high[joint] - back > slack or window_low[joint] != low:
                if back < low:
                    back = low
                if back > window_high[joint]:
                    back = window_high[joint]  # nor forward while opening
                window_low[joint], window_high[joint] = low, (back if back < high else high)
            reach = (low - position) / self.dt if position > low else 0.0
            target = target if target > reach else reach
        state.target_velocities[joint] = target
        state.forces[joint] = force
        state.position_gains[joint] = 0.0

    def _coupled_edge(self, joint: int, edge: float, sign: float, stop: float | None) -> float:
        """The front edge (rad) of an engaged finger joint its partner holds back: `edge`, where the
        coupling's play ends, not past `stop` (None: the joint's own). It never moves back: a joint
        already past `edge` is held where it was first held back (the worm's teeth do not ratchet on
        with the limit's give), and it moves on only by more than a worm slack at a time (each move
        costs a changeDynamics)."""
        state = self._state
        if stop is None:
            stop = self._joint_high[joint] if sign > 0.0 else self._joint_low[joint]
        current = state.window_high[joint] if sign > 0.0 else state.window_low[joint]
        held = current if sign * (stop - current) > 0.0 else state.positions[joint]
        if sign * (edge - held) <= self._slack:
            edge = held
        return edge if sign * (stop - edge) > 0.0 else stop

    def _palm_stop(self, inner: float) -> float:
        """Where the outer link's end meets the palm face (rad, outer joint) with the inner link at `inner`."""
        table, start = self._palm_table, self._palm_table_start
        if inner <= start:
            return table[0]
        place = (inner - start) / _PALM_TABLE_STEP
        index = int(place)
        if index >= len(table) - 1:
            return table[-1]
        fraction = place - index
        return table[index] + fraction * (table[index + 1] - table[index])

    def _palm_stop_inner(self, outer: float) -> float:
        """The inner link's angle (rad) at which the outer link, at `outer`, meets the palm face."""
        table, descending = self._palm_table, self._palm_table_descending
        index = bisect_left(descending, -outer)  # the first entry at or below `outer`
        if index == 0:
            return self._palm_table_start if table[0] <= outer else self._joint_high[1]
        if index >= len(table):
            return self._joint_high[1]
        above, below = table[index - 1], table[index]
        fraction = (above - outer) / (above - below) if above > below else 0.0
        return self._palm_table_start + (index - 1 + fraction) * _PALM_TABLE_STEP

    def _command_joints(self) -> None:
        """Joint targets, force limits and worm windows for this step from the drives and the clutch."""
        prm, state = self.params, self._state
        q, w, tau = state.positions, state.velocities, state.torques
        inner_open, inner_closed = self._inner_open, self._inner_closed
        outer_open, outer_closed = self._outer_open, self._outer_closed
        hold, drive_worm = self._hold, self._drive_worm
        dt, coupling_play = self.dt, self._coupling_play
        drive_on, drive_velocity, drive_fraction = state.drive_on, state.drive_velocity, state.drive_fraction
        locked_fingers, engaged, drive_capacity, at_stop = state.locked, state.engaged, state.drive_capacity, state.at_stop
        targets = state.target_velocities  # last step's, until drive_worm sets this step's
        for f, i2, i3 in FINGER_JOINTS:
            velocity = drive_velocity[f]
            fraction = drive_fraction[f]
            if not (drive_on[f] and velocity != 0.0 and fraction > 0.0):
                at_stop[f] = False
                if not locked_fingers[f]:
                    # The motor stops: the worms hold the finger where it is; a drive that was pushing
                    # a load closing leaves it wound up against that load.
                    locked_fingers[f] = True
                    t2, t3 = tau[i2], tau[i3]
                    squeeze = self._squeeze(f, t2 + t3 / 3.0 if engaged[f] else t3)
                    hold(i2, t2 if squeeze and t2 > 0.0 and engaged[f] else 0.0)
                    hold(i3, t3 if squeeze and t3 > 0.0 else 0.0)
                    drive_capacity[f] = 0.0
                continue
            locked_fingers[f] = False
            closing = velocity > 0.0
            sign = 1.0 if closing else -1.0
            if engaged[f]:
                capacity = fraction * self._finger_capacity
                drive_capacity[f] = sign * capacity
                omega = velocity / INNER_COUNTS_PER_RAD
                # One motor turns both worms: a link against its stop (or the palm) stalls the whole finger.
                palm = self._palm_stop(q[i2])
                inner_high, inner_low, outer_high, outer_low = self._palm_stop_inner(q[i3]) if closing else None, None, palm, None
                at_stop[f] = (q[i2] >= inner_closed or q[i3] >= (palm if palm < outer_closed else outer_closed)
                              ) if closing else q[i2] <= inner_open
                if at_stop[f]:
                    inner_target = outer_target = 0.0
                else:
                    ahead = q[i2] - 3.0 * q[i3]  # rad the inner link leads the 3:1 relation
                    correction = self._half_coupling_rate * ahead
                    inner_target, outer_target = omega - correction, (omega + correction) * _THIRD
                    # Neither joint runs ahead of the other by more than the gear's play: a link held
                    # back stops its partner (the whole finger stalls), however fast the motor is told
                    # to turn. The coupling correction may slow a joint, never turn it against the drive.
                    # A partner counts as held back when it ran at less than half the speed it was told
                    # last step (an obstacle); otherwise it goes on at its own share of the drive. (Its
                    # speed alone would make the two joints take turns: each one's room the other's
                    # last speed, zero when the other had no room, a limit cycle of two steps.)
                    partner_inner, partner_outer = sign * w[i2], sign * w[i3]  # how fast each partner is going along
                    told_inner, told_outer = sign * targets[i2], sign * targets[i3]
                    if partner_inner >= 0.5 * told_inner and sign * inner_target > partner_inner:
                        partner_inner = sign * inner_target
                    if partner_outer >= 0.5 * told_outer and sign * outer_target > partner_outer:
                        partner_outer = sign * outer_target
                    inner_room = 3.0 * (partner_outer if partner_outer > 0.0 else 0.0) + (coupling_play - sign * ahead) / dt
                    outer_room = ((partner_inner if partner_inner > 0.0 else 0.0) + (coupling_play + sign * ahead) / dt) * _THIRD
                    # A joint its partner holds back is held by the worms' teeth where the coupling's play
                    # ends (a velocity target of zero alone lets the solver's residual creep it on, 2°/s
                    # for an outer link beside an inner link stalled at full torque).
                    if sign * inner_target > inner_room:
                        inner_target = sign * inner_room
                        if inner_room < self._held_back_speed:
                            edge = self._coupled_edge(i2, 3.0 * q[i3] + sign * coupling_play, sign, inner_high)
                            inner_high, inner_low = (edge, None) if closing else (None, edge)
                    if sign * outer_target > outer_room:
                        outer_target = sign * outer_room
                        if outer_room < self._held_back_speed:
                            edge = self._coupled_edge(i3, (q[i2] + sign * coupling_play) * _THIRD, sign, outer_high if closing else None)
                            outer_high, outer_low = (edge, None) if closing else (palm, edge)
                    if sign * inner_target < 0.0:
                        inner_target = 0.0
                    if sign * outer_target < 0.0:
                        outer_target = 0.0
                # One motor: inner torque + outer torque / 3 within capacity (last step's loads).
                inner_floor, outer_floor = 0.05 * capacity, self._torque_floor_fraction * capacity
                inner_load, outer_load = sign * tau[i3], sign * tau[i2]
                inner_force = capacity - inner_load / 3.0 if inner_load > 0.0 else capacity
                outer_force = capacity - outer_load if outer_load > 0.0 else capacity
                drive_worm(i2, inner_target, inner_force if inner_force > inner_floor else inner_floor, sign,
                           inner_high, inner_low)
                drive_worm(i3, outer_target, 3.0 * (outer_force if outer_force > outer_floor else outer_floor), sign,
                           outer_high, outer_low)
            else:
                hold(i2)  # the inner link stays where the clutch let go (its load slipped)
                palm = self._palm_stop(q[i2])
                at_stop[f] = q[i3] >= (palm if palm < outer_closed else outer_closed) if closing else q[i3] <= outer_open
                capacity = fraction * self._outer_capacity
                drive_worm(i3, velocity / OUTER_ABS_COUNTS_PER_RAD, capacity, sign, palm)
                drive_capacity[f] = sign * capacity
        # Spread: back-drivable; F2 follows F1 through the gear constraint.
        s1, s2 = SPREAD_INDEX
        friction = prm.spread_friction_torque
        velocity = state.drive_velocity[3]
        self._drive(s2, 0.0, friction)
        if not state.drive_on[3]:
            self._drive(s1, 0.0, friction)
            return
        force = state.drive_fraction[3] * self._spread_capacity
        if force < friction:
            force = friction
        spread = q[s1]
        if (velocity > 0.0 and spread >= self._spread_high_stop) or (velocity < 0.0 and spread <= self._spread_low_stop):
            # Stalled at a stop: hold the stop itself (fighting PyBullet's limit row would drift).
            state.hold_positions[s1] = state.target_positions[s1] = self._spread_high if velocity > 0.0 else self._spread_low
            state.held[s1] = True
            state.target_velocities[s1], state.forces[s1], state.position_gains[s1] = 0.0, force, prm.lock_position_gain
        else:
            self._drive(s1, velocity / SPREAD_COUNTS_PER_RAD, force)
