"""A campaign: sorties levelled jointly, then gridded once in the campaign frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np

from pipeline.campaign.joint import JointLeveling, level_jointly
from pipeline.campaign.sorties import Sortie
from pipeline.defaults import default_field
from pipeline.errors import AeromagError
from pipeline.geo.igrf import main_field_direction
from pipeline.geo.projected import GridFrame
from pipeline.maps.grid import Grid, minimum_curvature
from pipeline.maps.level import Crossover


@dataclass
class CampaignSettings:
    """The campaign's gridding and levelling: the map stage's keys (``[map]``), one meaning."""

    cell_m: float | None = default_field("map", "cell_m", lambda v: v or None)  # None: spacing/4
    level_trend: bool = default_field("map", "level_trend")  # a slope per line besides its DC
    min_crossing_angle_deg: float = default_field("map", "min_crossing_angle_deg")
    mask_spacings: float = 1.0  # mask cells farther than this many line spacings from data
    crs_epsg: int | None = None  # the projected CRS (map.crs; None: the campaign's UTM zone)


@dataclass
class CampaignRun:
    """The joint levelling, the merged grid and what places it."""

    frame: GridFrame
    sorties: list[Sortie]
    leveling: JointLeveling
    spacing_m: float  # median of the flights' survey-line spacings
    grid: Grid
    # IGRF at the frame origin on the campaign's middle date: (total nT, incl., decl. deg)
    main_field: tuple[float, float, float] = (float("nan"),) * 3
    time_ns: int = 0  # the first sample of the campaign (the grids' log time)
    per_flight_grid: Grid | None = field(default=None, repr=False)
    warnings: list[str] = field(default_factory=list)

    def levelled_lines(self):
        """(sortie, line, levelled values nT) of every line after the joint corrections."""
        for s in self.sorties:
            for ln in s.lines:
                yield s, ln, ln.value_nT - self.leveling.correction(ln.line_id, ln.time_s)


def untied_groups(n_flights: int, xs: list[Crossover], between: np.ndarray) -> list[list[int]]:
    """The flights grouped by the between-flight crossovers that tie them (connected
    components); more than one group leaves the groups' relative levels undetermined."""
    from pipeline.campaign.joint import flight_of

    parent = list(range(n_flights))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for c, b in zip(xs, between, strict=True):
        if b:
            parent[root(flight_of(c.line_a))] = root(flight_of(c.line_b))
    groups: dict[int, list[int]] = {}
    for k in range(n_flights):
        groups.setdefault(root(k), []).append(k)
    return sorted(groups.values())


def _grid(points, cell_m: float, spacing_m: float, mask_spacings: float, crs: str) -> Grid:
    e, n, v = (np.concatenate([p[k] for p in points]) for k in range(3))
    return minimum_curvature(e, n, v, cell_m, mask_distance_m=mask_spacings * spacing_m, crs=crs)


def run_campaign(
    sorties: list[Sortie],
    frame: GridFrame,
    xs: list[Crossover],
    between: np.ndarray,
    settings: CampaignSettings | None = None,
    per_flight_grid: bool = False,
) -> CampaignRun:
    """Level every sortie jointly on the crossovers ``xs`` and grid the result once.

    Parameters
    ----------
    sorties : list of Sortie
        In the campaign frame ``frame`` (flight ``k`` is ``sorties[k]``).
    frame : GridFrame
        The campaign frame (:func:`pipeline.campaign.sorties.campaign_frame`).
    xs : list of Crossover
        Within- and between-flight crossovers (:func:`~pipeline.campaign.joint.sortie_crossovers`).
    between : ndarray of bool
        Per crossover: between two flights.
    settings : CampaignSettings, optional
        Cell (default: a quarter of the median line spacing), trend, masking.
    per_flight_grid : bool
        Also grid the flights as they came (each levelled on its own): the comparison the
        joint levelling is measured against.

    Returns
    -------
    CampaignRun

    Raises
    ------
    AeromagError
        No survey line spacing could be measured.
    """
    s = settings or CampaignSettings()
    times = {ln.line_id: ln.time_s for so in sorties for ln in so.lines}
    lev = level_jointly(times, len(sorties), xs, between, s.level_trend)
    spacings = [so.spacing_m for so in sorties if np.isfinite(so.spacing_m)]
    if not spacings:
        raise AeromagError(
            "no survey line spacing in any flight (each needs 2 or more survey lines)",
            file=str(sorties[0].path.parent),
        )
    spacing = float(np.median(spacings))
    cell = s.cell_m or spacing / 4.0
    pts = [
        (ln.east_m, ln.north_m, ln.value_nT - lev.correction(ln.line_id, ln.time_s))
        for so in sorties
        for ln in so.lines
    ]
    grid = _grid(pts, cell, spacing, s.mask_spacings, frame.grid_crs)
    before = None
    if per_flight_grid:
        raw = [(ln.east_m, ln.north_m, ln.value_nT) for so in sorties for ln in so.lines]
        before = _grid(raw, cell, spacing, s.mask_spacings, frame.grid_crs)
    t0 = min(so.time_range_s[0] for so in sorties)
    t1 = max(so.time_range_s[1] for so in sorties)
    when = datetime.fromtimestamp((t0 + t1) / 2, tz=UTC)
    _, total, incl, decl = main_field_direction(frame.lat0_deg, frame.lon0_deg, frame.alt0_m, when)
    warnings = []
    groups = untied_groups(len(sorties), xs, between)
    if len(groups) > 1:
        text = " | ".join(", ".join(sorties[k].name for k in g) for g in groups)
        warnings.append(
            f"no crossover ties these groups of flights to each other: {text}; their relative "
            "levels are not determined (the ridge keeps their offsets near 0): fly a tie line "
            "across the flights"
        )
    return CampaignRun(
        frame,
        sorties,
        lev,
        spacing,
        grid,
        (total, incl, decl),
        int(round(t0 * 1e9)),
        before,
        warnings,
    )
