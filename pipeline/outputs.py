"""Output channels: pipeline results as MCAP messages (schemas in ``schemas/``)."""

from __future__ import annotations

import numpy as np

from pipeline.compensate.stage import CompensationRun
from pipeline.io.reader import Flight
from pipeline.io.writer import OutputChannel
from pipeline.segment import Segmentation


def segment_channel(flight: Flight, seg: Segmentation) -> OutputChannel:
    """``/flight/segment``: one message at each change of label, line or manoeuvre."""
    ch = OutputChannel("/flight/segment", "aeromag.Segment")
    for i in seg.changes():
        h = seg.heading_deg[i]
        ch.add(int(flight.time_ns[i]), {
            "label": str(seg.label[i]), "line_id": str(seg.line_id[i]),
            "heading_deg": None if not np.isfinite(h) else round(float(h), 3),
            "manoeuvre": str(seg.manoeuvre[i]), "cardinal": str(seg.cardinal[i]),
            "calibration_pass": int(seg.calibration_pass[i]), "source": seg.source})
    return ch


def compensated_channel(flight: Flight, run: CompensationRun,
                        topic: str = "/mag/compensated") -> OutputChannel:
    """Compensated field at every epoch where it exists."""
    ch = OutputChannel(topic, "aeromag.CompensatedField")
    sensor = _sensor_id(flight)
    comp, inter, model = run.compensated_nT, run.interference_nT, run.model.model
    for i in np.flatnonzero(np.isfinite(comp)):
        ch.add(int(flight.time_ns[i]), {"sensor_id": sensor, "total_nT": float(comp[i]),
                                         "interference_nT": float(inter[i]), "model": model})
    return ch


def model_message(flight: Flight, run: CompensationRun, ch: OutputChannel | None = None
                  ) -> OutputChannel:
    """``/compensation/model``: the fitted model (one message, at the first epoch)."""
    ch = ch or OutputChannel("/compensation/model", "aeromag.CompensationModel")
    m = run.model.to_dict()
    fom = run.fom.total if run.fom else {"uncompensated": None, "compensated": None}
    payload = {"sensor_id": _sensor_id(flight), "fom_nT": fom,
               **{k: m[k] for k in ("model", "terms", "coefficients", "compensating_terms",
                                    "lambda", "band_hz", "poles", "trim", "samples",
                                    "fit_residual_nT", "calibration_windows_s",
                                    "gradient_nT_per_m")}}
    # one ns apart so several models on the topic keep their order
    ch.add(int(flight.time_ns[0]) + len(ch.messages), payload)
    return ch


def _sensor_id(flight: Flight) -> str:
    s = flight.series[flight.topic_of["scalar"]]
    return str(s.labels["sensor_id"][0]) if s.labels["sensor_id"].size else ""
