r"""ETSI reactive decentralized congestion control (DCC): a sender's minimum message interval by CBR state.

The reactive approach of ETSI TS 102 687 (ITS-G5 access layer DCC): each station samples its channel
busy ratio every :math:`T_{samp}` = 100 ms (NDL_minDccSampling), and a state machine maps it to a
state with a minimum interval between its packets (the "gatekeeper"). The state rises when the
*minimum* CBR of the last second is above a state's threshold, and falls when the *maximum* CBR of the
last five seconds is below it (hysteresis: sustained load raises it, sustained quiet lowers it).

Default table (:class:`DccParams`): the seven states of the reactive state machine as implemented by
Vanetza's ``dcc::StateMachine`` (the ETSI stack of the Artery simulator): Relaxed below CBR 0.19 at
60 ms; Active 1-5 from 0.19, 0.27, 0.35, 0.43, 0.51 at 100, 180, 260, 340, 420 ms; Restrictive from
0.59 at 460 ms. The ETSI document's own table (clause and version) could not be read for this work;
the thresholds and intervals are configuration (``dcc:`` of a radio profile) so another table is a
YAML change.

Gatekeeper: a packet offered before the interval since the sender's previous packet has passed is not
sent (dropped with cause ``dcc``; ETSI's gatekeeper may instead hold one packet per queue until the
gate opens, which sends at the same rate with up to one interval of extra delay).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["DccParams", "ReactiveDcc"]


class DccParams(BaseModel):
    """Reactive DCC table (``radio.dcc`` of a profile); off unless ``enabled``."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    enabled: bool = False
    thresholds: tuple[float, ...] = Field(
        (0.19, 0.27, 0.35, 0.43, 0.51, 0.59), description="CBR lower bound of each state above Relaxed"
    )
    intervals_s: tuple[float, ...] = Field(
        (0.06, 0.10, 0.18, 0.26, 0.34, 0.42, 0.46), description="per state, Relaxed first"
    )
    up_window_s: float = Field(1.0, gt=0, description="rise on the minimum CBR over this window")
    down_window_s: float = Field(5.0, gt=0, description="fall on the maximum CBR over this window")

    @model_validator(mode="after")
    def _table(self) -> DccParams:
        if len(self.intervals_s) != len(self.thresholds) + 1:
            raise ValueError(f"{len(self.thresholds)} thresholds need {len(self.thresholds) + 1} intervals_s")
        if list(self.thresholds) != sorted(self.thresholds) or list(self.intervals_s) != sorted(self.intervals_s):
            raise ValueError("thresholds and intervals_s must rise with the state")
        return self


class ReactiveDcc:
    """One sender's reactive DCC: ``update(t, cbr)`` every sample, ``allow(t)`` before each packet."""

    def __init__(self, params: DccParams) -> None:
        self.params = params
        self.state = 0
        self._samples: deque[tuple[float, float]] = deque()
        self._last_tx: float | None = None
        self.gated = 0

    @property
    def interval_s(self) -> float:
        return self.params.intervals_s[self.state]

    def update(self, t: float, cbr: float) -> int:
        """Add a CBR sample at ``t``; returns the state (0 = Relaxed)."""
        p = self.params
        self._samples.append((t, float(cbr)))
        while self._samples and self._samples[0][0] < t - p.down_window_s - 1e-9:
            self._samples.popleft()
        recent = [c for ts, c in self._samples if ts >= t - p.up_window_s - 1e-9]
        up = int(np.searchsorted(p.thresholds, min(recent), side="right"))
        down = int(np.searchsorted(p.thresholds, max(c for _, c in self._samples), side="right"))
        if up > self.state:
            self.state = up
        elif down < self.state:
            self.state = down
        return self.state

    def allow(self, t: float) -> bool:
        """May a packet go at ``t``? If so it is counted as sent."""
        if self._last_tx is not None and t - self._last_tx < self.interval_s - 1e-6:
            self.gated += 1
            return False
        self._last_tx = t
        return True
