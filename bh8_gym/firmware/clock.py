"""The firmware's simulated clock: tasks (a motion, a RealTime cycle) are generators that yield the
time they next wake at; between wake-ups the plant steps at its own rate, each step driven by the
HCTL channels (motion_control.MotorChannel)."""
from __future__ import annotations

TIME_EPS = 1e-9  # seconds: a physics step ending this close to a deadline still runs


class SimulatedClock:
    """Runs the current task and the physics up to a deadline (uses `_task`, `_wake`, `time`,
    `_physics_time`, `_steps`, `_channel_list`, the plant)."""

    def _run(self, deadline: float | None, busy_limit: float | None = None) -> None:
        """Run until `deadline` (None: until idle), or until `busy_limit` while a command runs."""
        while True:
            if self._task is None:
                self._consume_input()
                if self._task is None:
                    if deadline is not None and deadline > self.time:
                        self._advance_to(deadline)
                    return
            if deadline is not None and self._wake > deadline:
                self._advance_to(deadline)
                return
            if busy_limit is not None and self._wake > busy_limit:
                self._advance_to(busy_limit)
                return
            self._advance_to(self._wake)
            try:
                self._wake = next(self._task)
            except StopIteration:
                self._task = None

    def _start_task(self, task) -> None:
        try:
            self._wake = next(task)
        except StopIteration:
            return
        self._task = task

    def _advance_to(self, t: float) -> None:
        if t <= self.time:
            return
        step_end = self._physics_time + self._dt
        while step_end <= t + TIME_EPS:
            self._physics_step()
            step_end = self._physics_time + self._dt
        self.time = t

    def _physics_step(self) -> None:
        positions, velocities = self._positions, self._velocities
        origin, last, odometer = self._origin, self._last_positions, self._odometer
        drive_v, drive_f = self._drive_velocities, self._drive_fractions
        t, dt = self._physics_time, self._dt
        for i, channel in enumerate(self._channel_list):
            position = positions[i]
            odometer[i] += abs(position - last[i])
            last[i] = position
            drive_v[i], drive_f[i] = channel.drive(t, position - origin[i], velocities[i], dt)
        self._positions, self._velocities = self.plant.step_with_drives(drive_v, drive_f)
        self._steps += 1
        self._physics_time = self._time_base + self._steps * dt

    def _refresh_plant_state(self) -> None:
        self._positions, self._velocities = self.plant.motor_state_lists()
