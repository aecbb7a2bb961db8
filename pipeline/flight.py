"""The aligned flight: every stream of a recording on the scalar magnetometer's epochs.

:class:`Flight` is what :func:`pipeline.io.read_flight` returns and what every stage takes.
It lives outside :mod:`pipeline.io` so stages can name the type without importing the reader;
``pipeline.io.reader.Flight`` and ``pipeline.io.Flight`` remain as re-exports. The types of its
fields come from the leaf :mod:`pipeline.io.series`, never from the reader.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import AeromagError

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

    from pipeline.io.series import Gap, Loss, TopicSeries


@dataclass
class Flight:
    """A recording's streams on one time base: the primary scalar magnetometer's epochs.

    Columns of ``data`` (those whose topic is absent are missing, not NaN-filled):

    - ``time_s``: seconds since the first epoch; ``time_ns`` holds absolute UTC ns.
    - ``scalar_nT``: primary scalar magnetometer; ``scalar_<id>_nT`` for others.
    - ``vector_x_nT``, ``vector_y_nT``, ``vector_z_nT``: primary vector magnetometer, body frame
      (x forward, y right, z down); ``vector_<id>_x_nT`` ... for others.
    - ``roll_deg``, ``pitch_deg``, ``yaw_deg``: attitude (yaw = true heading, 0-360).
    - ``lat_deg``, ``lon_deg``, ``alt_m``: GNSS, WGS-84 (altitude above the ellipsoid).
    - ``base_nT``: base-station magnetometer.
    - ``aux_<name>``: auxiliary channels, unit in ``units``.
    - ``plan_line_id``, ``plan_kind``: the planned segment in force (from ``/plan/line``).
    - ``reference_<name>_nT``: another processor's product (``/reference/<name>``).

    Secondary streams are linearly interpolated (yaw unwrapped first); epochs outside a
    stream's span or inside one of its gaps are NaN and listed in ``notes``.
    """

    source: Path
    time_ns: np.ndarray
    data: pd.DataFrame
    units: dict[str, str]
    series: dict[str, TopicSeries]
    topic_of: dict[str, str]  # role or column group -> topic used
    gaps: list[Gap]
    notes: list[str]
    unknown_topics: list[str]
    losses: list[Loss] = field(default_factory=list)  # damaged parts of the file, salvaged
    all_topics: list[str] = field(default_factory=list)  # every topic in the file

    def has(self, *columns: str) -> bool:
        """True when every named column is present (its channel was recorded).

        Parameters
        ----------
        *columns : str
            Column names of ``data``, e.g. ``"vector_x_nT"`` (body frame, nT) or ``"lat_deg"``.

        Returns
        -------
        bool
        """
        return all(c in self.data.columns for c in columns)

    def require(self, *columns: str, purpose: str) -> None:
        """Raise a one-line error when a needed column (hence channel) is missing."""
        missing = [c for c in columns if c not in self.data.columns]
        if missing:
            raise AeromagError(
                f"{purpose} needs {', '.join(missing)} but the channel is absent",
                file=self.source,
                channel=_CHANNEL_OF_COLUMN.get(missing[0], ""),
            )


_CHANNEL_OF_COLUMN = {
    "vector_x_nT": "/mag/vector",
    "vector_y_nT": "/mag/vector",
    "vector_z_nT": "/mag/vector",
    "roll_deg": "/ins/attitude",
    "pitch_deg": "/ins/attitude",
    "yaw_deg": "/ins/attitude",
    "lat_deg": "/gnss/fix",
    "lon_deg": "/gnss/fix",
    "alt_m": "/gnss/fix",
    "base_nT": "/base/scalar",
}
