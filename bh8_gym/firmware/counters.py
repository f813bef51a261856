"""The counters the hand keeps through power failures (manual §5.4.1 OD, PTEMP, UPSECS) and the
temperature the firmware reads, persisted in the NVStore with the parameter sets."""
from __future__ import annotations

from bh8_gym.protocol import MOTORS


class StoredCounters:
    """Odometer, peak temperature and uptime of `Firmware`, and the one store write that saves them
    (uses `store`, `_odometer`, `_peak_temperature`, `_uptime_base`, `_boot_time`, `time`, the plant)."""

    def _save(self, motors=(), global_values: bool = False) -> None:
        """One store write: the counters, plus the parameter sets of `motors` and/or the globals."""
        uptime = self._uptime_seconds()
        try:
            peak = self._update_peak_temperature()
        except ValueError:  # a NaN temperature (the physics failed): the counters are saved all the same
            peak = self._peak_temperature
        self.store.save((dict(zip(MOTORS, self._odometer)), peak, uptime),
                        motors={m: self._motor_values[m] for m in motors},
                        global_values=self._globals if global_values else None)
        self._uptime_base = uptime
        self._boot_time = self.time

    def _uptime_seconds(self) -> float:
        return self._uptime_base + (self.time - self._boot_time)

    def _temperature_tenths(self) -> int:
        return max(-550, min(1250, int(round(self.plant.temperature * 10.0))))

    def _update_peak_temperature(self) -> int:
        temp = self._temperature_tenths()
        if temp > self._peak_temperature:
            self._peak_temperature = temp
        return self._peak_temperature
