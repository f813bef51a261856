"""RealTime mode (manual §6, SPEC.md §5-§7): LOOP entry and exit, control blocks applied to the
motors, feedback blocks built, on the SPEC.md §6 time model (bytes on the line, processing time).

Choices where the documents are silent (SPEC.md §5-§8):

- RealTime (§6, SPEC.md §5-§6): LOOP answers the echo then "*" at once. ^C leaves LOOP with the
  reply "\\n\\r=> " and no ERR line (§6.4: "the hand will respond by printing a prompt"). A bad
  header answers "\\n\\rERR 2048\\n\\r=> ". Leaving LOOP applies HOLD to the LOOP motors. On
  entering LOOP the motors run at velocity 0 with gain FPG until a control block sets them; a
  motor whose LCPG flag is 0 keeps FPG as its gain. Firmware 4.4 LCT is a position-mode datum
  (SPEC.md §7, from Barrett's API documentation): each control block's LCT is added to the motor's
  present position and the sum becomes the commanded position, servoed with gain FPG (so the
  torque is FPG/4 × LCT, saturating at full duty); before the first block an LCT motor holds where
  it is. LFBP reports BP (below); LFAIN reads 0 (no analog input is modelled).
- The RealTime cycle_hook runs at the start of every cycle, before the control block's time.
- Only FGET P sets the RealTime "reported position" (§6.2.3); FLISTV does not. With LFDPD set, the
  reported position becomes the present one every cycle: the part of a change LFDP cannot carry,
  overflow or the remainder below LFDPC, is discarded (§5.4.3 LFDPD: "any position change that
  cannot be sent in a delta position datum is discarded").
- LFV is the HCTL's actual velocity, whole encoder counts per sample (§6.2.2: "all integer";
  the HCTL-1100 computes it as the position change over one sample), the nearest to the motor's
  speed, then divided by LFVC as C divides (towards zero); SPEC.md §4 derives what it reads.
- LFAP is an unsigned word (SPEC.md §5): a position below 0 (a finger opened past its home, e.g.
  right after HI) is sent as 0, above 65535 as 65535; FGET P reports the signed value.
"""
from __future__ import annotations

from bh8_gym.parameters import coefficient
from bh8_gym.motion_control import VELOCITY_SCALE
from bh8_gym.protocol import CTRL_C, LINE_END, PROMPT, seconds_per_byte
from bh8_gym.realtime_codec import HEADERS_WITH_FEEDBACK, LoopLayout
from bh8_gym.status import Status


class RealTimeLoop:
    """LOOP mode of `Firmware`: `_loop_layout` is set while in LOOP; each complete control block
    starts `_cycle_task` (uses `_channels`, `_motor_values`, `_globals`, `_reported_position`, the plant)."""

    def _enter_loop(self, layout: LoopLayout) -> None:
        self._loop_layout = layout
        values = self._motor_values
        self._loop_velocity = {m: 0.0 for m in layout.motors}
        self._loop_gain = {m: values[m]["FPG"] for m in layout.motors}
        for m in layout.motors:
            channel = self._channels[m]
            channel.set_sample(values[m]["SAMPLE"])
            if self.profile == "4.4" and layout.flags[m].LCT:
                channel.hold(self._position(m), values[m]["FPG"])  # datum 0: stay
            else:
                channel.velocity(0.0, self._loop_gain[m], loop=True)
            self._status[m] = 0
        self._loop_velocity_scale = {m: coefficient(values[m]["LCVC"]) / VELOCITY_SCALE for m in layout.motors}
        # Fixed while in LOOP (parameters change only in supervisory mode): looked up once, not per cycle.
        self._seconds_per_byte = seconds_per_byte(self.baud)
        self._feedback_plan = [
            (name, m, self._channels[m].period, values[m]["SGFLIP"], coefficient(values[m]["LFVC"]),
             coefficient(values[m]["LFDPC"])) if m is not None else (name, m, 0.0, 0, 1, 1)  # LFT: no motor
            for m, name in layout.feedback_fields
        ]
        self._output += b"*"
        if self.loop_entry_hook is not None:
            self.loop_entry_hook(self, layout)

    def _leave_loop(self) -> None:
        layout = self._loop_layout
        self._loop_layout = None
        for m in layout.motors:
            self._terminate(m, self._position(m))

    def _consume_loop_block(self) -> bool:
        """Start a cycle for a complete control block; False while a block is incomplete."""
        data = self._input
        header = data[0]
        if header == CTRL_C:
            del data[0]
            self._leave_loop()
            self._output += LINE_END + PROMPT
            return True
        if header not in b"CcAa":
            del data[0]
            self._leave_loop()
            self._reply(error=Status.INVALID_REALTIME_HEADER)
            return True
        size = self._loop_layout.control_block_size(header)
        if len(data) < size:
            return False
        block = bytes(data[:size])
        del data[:size]
        self._start_task(self._cycle_task(block))
        return True

    def _cycle_task(self, block: bytes):
        """One RealTime cycle on the SPEC.md §6 time model."""
        if self.cycle_hook is not None:
            self.cycle_hook(self)
        layout = self._loop_layout
        header = block[0]
        seconds_per_byte = self._seconds_per_byte
        feedback_size = layout.feedback_size if header in HEADERS_WITH_FEEDBACK else 1
        yield self.time + len(block) * seconds_per_byte
        if len(block) > 1:
            self._apply_control(layout, layout.decode_control(block[1:]))
        yield self.time + self.processing_time
        if header in HEADERS_WITH_FEEDBACK:
            self._output += layout.encode_feedback(self._feedback_values())
        else:
            self._output += b"*"
        yield self.time + feedback_size * seconds_per_byte

    def _apply_control(self, layout: LoopLayout, values) -> None:
        velocity = self._loop_velocity
        gain = self._loop_gain
        torque = None
        for (m, name), value in zip(layout.control_fields, values):
            if name == "LCV":
                velocity[m] = value * self._loop_velocity_scale[m]
            elif name == "LCPG":
                gain[m] = value
            else:  # LCT (4.4)
                if torque is None:
                    torque = {}
                torque[m] = value
        for m in layout.motors:
            if torque is not None and m in torque:
                # SPEC.md §7: LCT is added to the present position; the sum is the commanded position
                self._channels[m].hold(self._position(m) + torque[m], self._motor_values[m]["FPG"])
            else:
                self._channels[m].velocity(velocity[m], gain[m], loop=True)

    def _feedback_values(self) -> list[int]:
        out = []
        append = out.append
        strain = None
        positions, origin, velocities = self._positions, self._origin, self._velocities
        lfdpd = self._globals["LFDPD"]
        for name, m, period, sgflip, lfvc, lfdpc in self._feedback_plan:
            if name == "LFAP":
                position = round(positions[m - 1] - origin[m - 1])
                append(0 if position < 0 else (65535 if position > 65535 else position))
            elif name == "LFS":
                if strain is None:
                    strain = self.plant.strain_gauges_list()
                sg = strain[m - 1]
                append(255 - sg if sgflip else sg)
            elif name == "LFV":
                # The HCTL's actual velocity: whole counts moved in one sample (§6.2.2 "all integer"),
                # the nearest to the speed (a finger at 3.98 counts/sample moves 4 in most samples)
                per_sample = round(velocities[m - 1] * period)
                scaled = int(per_sample / lfvc)
                append(-128 if scaled < -128 else (127 if scaled > 127 else scaled))
            elif name == "LFDP":
                append(self._delta_position(m, lfdpc, lfdpd))
            elif name == "LFBP":
                append(self._breakaway_position(m))
            elif name == "LFAIN":
                append(0)
            else:  # LFT
                if self.profile == "4.4":
                    append(max(-128, min(127, int(round(self.plant.temperature)))))
                else:
                    append(self._temperature_tenths())
        self._update_peak_temperature()
        return out

    def _delta_position(self, m: int, scale: int, discard: int) -> int:
        """§6.2.3: (present − reported) / LFDPC clipped to a signed byte; reported follows."""
        present = int(round(self._position(m)))
        difference = present - self._reported_position[m]
        datum = int(difference / scale)
        datum = max(-128, min(127, datum))
        if discard:
            self._reported_position[m] = present
        else:
            self._reported_position[m] += datum * scale
        return datum
