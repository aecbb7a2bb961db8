"""Decisions between a catalogue effect and a nuisance of the null model that mimics it.

A late sensor and eddy currents that decay with a time constant both leave a residual that
follows the attitude's rate of change. Physics separates them: a lag delays everything the
sensor sees (the permanent and induced interference's response to the attitude, the geology
along the lines, the field the fluxgate predicts), a decay delays only the eddy terms. With
the decay in the null model (its time constant chosen on held-out data), a true lag still
lowers the held-out residual, for the decay cannot delay the permanent and induced terms;
a decay mistaken for a lag does not. Where neither adds to the other on held-out data but
each alone explains the residual, the two are weighed as rivals in the forms the null
model would take them: the lag model (the whole reading delayed) against the decay model
(the decayed eddy columns beside T-L's); the one that predicts held-out calibration data
better by the audit's test is the explanation (held-out prediction weighs the decay's extra
coefficients). When neither wins, the
timing along the lines (survey crossovers, the fluxgate's record of the same anomalies)
decides when it holds the lag and excludes none; otherwise the tie is reported as an
ambiguity and nothing is named for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pipeline.compensate.heldout import HeldOut

LAG = "sensor_lag"
DECAY = "eddy_decay"


def significant(h: HeldOut | None, alpha: float, min_gain: float) -> bool:
    """Whether a held-out comparison shows a gain: one-sided p below ``alpha`` and at least
    ``min_gain`` of the held-out RMS removed."""
    return h is not None and h.p_value < alpha and h.reduction >= min_gain


@dataclass
class LagVersusDecay:
    """The held-out comparisons between a lag and the null model's eddy decay.

    Attributes
    ----------
    lag_beyond_null : HeldOut
        The lag beside the null model with the decay in it.
    lag_alone : HeldOut or None
        The lag beside the null model without the decay (None when not weighed).
    decay_alone : HeldOut
        The decay beside the null model without it (the lag out as well).
    decay_beyond_lag : HeldOut
        The decay beside the null model without it plus the lag.
    lag_over_decay, decay_over_lag : HeldOut or None
        The lag model against the decay model (the null model's form), and the reverse
        (None when not weighed: no tie).
    """

    lag_beyond_null: HeldOut
    lag_alone: HeldOut | None  # None: not needed (the lag beats the null with the decay)
    decay_alone: HeldOut
    decay_beyond_lag: HeldOut
    lag_over_decay: HeldOut | None = None
    decay_over_lag: HeldOut | None = None

    def tie(self, alpha: float, min_gain: float) -> bool:
        """Whether each explains the residual alone and the decay adds nothing to the lag."""
        return (
            significant(self.lag_alone, alpha, min_gain)
            and significant(self.decay_alone, alpha, min_gain)
            and not significant(self.decay_beyond_lag, alpha, min_gain)
        )

    def lag_dominates(self, alpha: float, min_gain: float) -> bool:
        """Whether the lag explains what the decay does and more: it lowers held-out data
        beside the decay, and the decay adds nothing beside it."""
        return significant(self.lag_beyond_null, alpha, min_gain) and not significant(
            self.decay_beyond_lag, alpha, min_gain
        )

    def verdict(self, alpha: float, min_gain: float, timing: str) -> str:
        """``"lag"`` (named), ``"ambiguous"`` (a tie the data cannot break) or ``"none"``.

        The lag is named when it lowers held-out data beside the decay. When the two tie
        (each explains the residual alone, neither adds to the other) the rival that
        predicts held-out data better is the explanation
        (``lag_over_decay``, ``decay_over_lag``); when neither does, the timing along the
        lines decides: ``timing`` is ``"holds"`` (a significant timing lag whose interval holds
        the calibration's), ``"excludes"`` (the timing's interval lies below the lag: the
        sensor is not that late) or ``"silent"``.
        """
        if significant(self.lag_beyond_null, alpha, min_gain):
            return "lag"
        if not self.tie(alpha, min_gain):
            return "none"
        if significant(self.lag_over_decay, alpha, min_gain):
            return "lag"
        if significant(self.decay_over_lag, alpha, min_gain) or timing == "excludes":
            return "none"
        return "lag" if timing == "holds" else "ambiguous"

    def ambiguity(self) -> dict[str, Any]:
        """The contract's record of the tie: ``{"candidates", "heldout_gain"}`` (fractions
        of the held-out RMS each removes alone, beside the null model without the other)."""
        return {
            "candidates": [LAG, DECAY],
            "heldout_gain": {
                LAG: self.lag_alone.reduction if self.lag_alone is not None else 0.0,
                DECAY: self.decay_alone.reduction,
            },
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: each comparison's figures."""
        return {
            "lag_beyond_null": self.lag_beyond_null.to_dict(),
            "lag_alone": None if self.lag_alone is None else self.lag_alone.to_dict(),
            "decay_alone": self.decay_alone.to_dict(),
            "decay_beyond_lag": self.decay_beyond_lag.to_dict(),
            "lag_over_decay": None
            if self.lag_over_decay is None
            else self.lag_over_decay.to_dict(),
            "decay_over_lag": None
            if self.decay_over_lag is None
            else self.decay_over_lag.to_dict(),
        }
