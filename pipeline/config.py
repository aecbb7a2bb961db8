"""The processing configuration: one TOML file with every parameter of the post-flight flow.

Defaults live in ``pipeline/default_config.toml`` (shipped with the package); a user file
overrides any of them. Unknown keys and wrong types are errors naming the file and key. The
hash of the resolved values identifies a configuration in outputs and in the archive index.
"""

from __future__ import annotations

import copy
import hashlib
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# moved to pipeline.defaults (no config <-> io import cycle); re-exported here
from pipeline.defaults import default_text as default_text
from pipeline.defaults import default_value as default_value
from pipeline.defaults import read_toml as read_toml
from pipeline.defaults import ridge_problem
from pipeline.errors import AeromagError

CONFIG_VERSION = 1

# keys that counted samples for a physical time, now in seconds: an old key is an error naming
# its replacement (a sample count means a different time at every rate, so it is not converted)
RENAMED = {
    "compensation.trim": "compensation.trim_s (seconds; 20 samples at 10 Hz is 2.0)",
    "despike.window_samples": "despike.window_s (seconds; 101 samples at 10 Hz is 10.0)",
    "vector.fuzzy_window": "vector.fuzzy_window_s (seconds; 30 samples at 10 Hz is 3.0)",
}


def _merge(base: dict, over: dict, source: str, prefix: str = "") -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        key = f"{prefix}{k}"
        if key in RENAMED:
            raise AeromagError(f"{key} (samples) was replaced by {RENAMED[key]}", file=source)
        if k not in base:
            raise AeromagError(f"unknown configuration key {key!r}", file=source)
        if isinstance(base[k], dict):
            if not isinstance(v, dict):
                raise AeromagError(f"{key} must be a table", file=source)
            out[k] = _merge(base[k], v, source, key + ".")
            continue
        b = base[k]
        ok = (
            isinstance(v, bool)
            if isinstance(b, bool)
            else isinstance(v, int | float) and not isinstance(v, bool)
            if isinstance(b, float)
            else isinstance(v, type(b))
        )
        if key == "compensation.ridge":  # the one place a ridge value is checked
            if ridge_problem(v):
                raise AeromagError(f'{key} = {v!r}: use "auto" or a number >= 0', file=source)
            ok = True
        if not ok:
            raise AeromagError(f"{key} = {v!r}: expected {type(b).__name__}", file=source)
        out[k] = float(v) if isinstance(b, float) and not isinstance(v, str) else v
    return out


@dataclass(frozen=True)
class Config:
    """The resolved configuration: the shipped defaults (``default_config.toml``) merged with
    a user's TOML file, and where it came from (``source``: ``defaults``, a path, or the
    command line). Each stage's settings dataclass is built from it (``*_settings``)."""

    values: dict[str, Any]
    source: str

    @classmethod
    def load(cls, path: str | Path | None = None) -> Config:
        """The defaults, merged with the TOML file at ``path`` when given.

        Raises
        ------
        AeromagError
            An unreadable file, an unknown key, a wrong type or an unsupported
            ``config_version`` (one line naming the file).
        """
        base = tomllib.loads(default_text())
        if path is None:
            return cls(base, "defaults")
        p = Path(path)
        user = read_toml(p, "configuration")
        values = _merge(base, user, str(p))
        if values["config_version"] != CONFIG_VERSION:
            raise AeromagError(
                f"config_version {values['config_version']} is not supported "
                f"(this aeromag reads {CONFIG_VERSION})",
                file=p,
            )
        return cls(values, str(p))

    def with_values(self, changes: dict[str, Any], source: str = "command line") -> Config:
        """A copy with ``changes`` (``{"section.key": value}``) applied, checked like a file's
        values (unknown keys and wrong types are errors naming ``source``); the single-stage
        commands' options override configuration keys this way."""
        nested: dict[str, Any] = {}
        for dotted, v in changes.items():
            section, _, key = dotted.rpartition(".")
            (nested.setdefault(section, {}) if section else nested)[key] = v
        values = _merge(self.values, nested, source)
        label = (
            self.source
            if not changes
            else (f"{self.source} + {source}" if self.source != "defaults" else source)
        )
        return Config(values, label)

    @property
    def hash(self) -> str:
        """SHA-256 of the resolved values (canonical JSON): tags every output of a run."""
        canon = json.dumps(self.values, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canon.encode()).hexdigest()

    def __getitem__(self, key: str) -> Any:
        return self.values[key]

    # -- stage settings -----------------------------------------------------------------------
    def fit_settings(self, model: str):
        """:class:`pipeline.compensate.FitSettings` of ``model`` from ``[compensation]``."""
        from pipeline.compensate import FitSettings

        c = self.values["compensation"]
        return FitSettings(
            model=model,
            band_hz=tuple(c["band_hz"]),
            poles=c["poles"],
            trim_s=c["trim_s"],
            ridge=c["ridge"],
            base=c["agg_base"],
            agg_gradient=c["agg_gradient"],
            bt_scale_nT=c["bt_scale_nT"],
            extension_alpha=c["extension_alpha"],
            extension_min_gain=c["extension_min_gain"],
            level_guard_alpha=c["level_guard_alpha"],
            heading_levels_alpha=c["heading_levels_alpha"],
            learner=c["learner"],
        )

    def map_settings(self):
        """:class:`pipeline.maps.stage.MapSettings` from ``[map]``."""
        from pipeline.geo.projected import parse_crs_setting
        from pipeline.maps.stage import MapSettings, parse_arima

        m = self.values["map"]
        return MapSettings(
            cell_m=m["cell_m"] or None,
            crs_epsg=parse_crs_setting(m["crs"], self.source),
            arima=parse_arima(m["arima"]),
            noise_nT=m["noise_nT"] or None,
            level_trend=m["level_trend"],
            direction=m["direction"],
            min_crossing_angle_deg=m["min_crossing_angle_deg"],
            gridder=m["gridder"],
            dem_path=m["dem_path"],
            dem_clearance_m=m["dem_clearance_m"],
            microlevel=m["microlevel"],
            microlevel_wavelength_m=m["microlevel_wavelength_m"],
            microlevel_along_m=m["microlevel_along_m"],
            microlevel_clip_nT=m["microlevel_clip_nT"],
        )

    def campaign_settings(self):
        """The campaign's settings: the map stage's cell, trend and crossing angle."""
        from pipeline.campaign.stage import CampaignSettings
        from pipeline.geo.projected import parse_crs_setting

        m = self.values["map"]
        return CampaignSettings(
            cell_m=m["cell_m"] or None,
            crs_epsg=parse_crs_setting(m["crs"], self.source),
            level_trend=m["level_trend"],
            min_crossing_angle_deg=m["min_crossing_angle_deg"],
        )

    def enhance_settings(self):
        """:class:`pipeline.maps.enhance.EnhanceSettings` from ``[enhance]``."""
        from pipeline.maps.enhance import EnhanceSettings, parse_products

        e = self.values["enhance"]
        return EnhanceSettings(products=parse_products(e["products"]), source=e["source"])

    def navigation_settings(self):
        """The post-flight flow's navigation settings (``[navigate]``; validation lines)."""
        from pipeline.navigation.stage import NavigationSettings

        n = self.values["navigate"]
        return NavigationSettings(
            filter=n["filter"],
            ins=n["ins"],
            seed=n["seed"],
            default_map_sigma_nT=n["map_sigma_nT"],
            map_error_length_m=n["map_error_length_m"],
            gate_probability=n["gate_probability"],
        )

    def despike_settings(self):
        """:class:`pipeline.despike.DespikeSettings` from ``[despike]``."""
        from pipeline.despike import DespikeSettings

        return DespikeSettings(**self.values["despike"])

    def quality_settings(self):
        """:class:`pipeline.quality.QualitySettings` from ``[quality]`` (and the map's
        crossing angle and CRS)."""
        from pipeline.geo.projected import parse_crs_setting
        from pipeline.quality import QualitySettings

        return QualitySettings(
            **self.values["quality"],
            min_crossing_angle_deg=self.values["map"]["min_crossing_angle_deg"],
            crs_epsg=parse_crs_setting(self.values["map"]["crs"], self.source),
        )

    def audit_settings(self):
        """:class:`pipeline.audit.AuditSettings` from ``[audit]`` and the compensation band."""
        from pipeline.audit import AuditSettings
        from pipeline.audit.extended import BandSettings

        a, c = self.values["audit"], self.values["compensation"]
        return AuditSettings(
            baseline=a["baseline"],
            alpha=a["alpha"],
            min_gain=a["min_gain"],
            band=BandSettings(tuple(c["band_hz"]), c["poles"], c["trim_s"]),
            flight_alpha=a["flight_alpha"],
            null_draws=a["null_draws"],
            null_seed=a["null_seed"],
            min_nuisance_nT=a["min_nuisance_nT"],
            min_survey_effect_nT=a["min_survey_effect_nT"],
        )

    def validate(self) -> None:
        """Check values that types alone do not (raises AeromagError)."""
        from pipeline.compensate import MODELS
        from pipeline.vector.stage import METHODS

        c = self.values["compensation"]
        bad = [m for m in c["models"] if m not in MODELS]
        if bad or not c["models"]:
            raise AeromagError(
                f"compensation.models: use some of {', '.join(MODELS)}", file=self.source
            )
        if self.values["vector"]["method"] not in METHODS:
            raise AeromagError(f"vector.method: use one of {', '.join(METHODS)}", file=self.source)
        if self.values["map"]["direction"] not in ("smooth", "both", "forward"):
            raise AeromagError(
                "map.direction: use smooth (both is its old name) or forward", file=self.source
            )
        if self.values["map"]["gridder"] not in ("minimum_curvature", "equivalent_sources", "auto"):
            raise AeromagError(
                "map.gridder: use minimum_curvature, equivalent_sources or auto", file=self.source
            )
        if not 0.0 <= self.values["map"]["min_crossing_angle_deg"] <= 90.0:
            raise AeromagError("map.min_crossing_angle_deg: use 0 to 90 degrees", file=self.source)
        band = c["band_hz"]
        if (
            len(band) != 2
            or not all(isinstance(b, int | float) and not isinstance(b, bool) for b in band)
            or not 0 < band[0] < band[1]
        ):
            raise AeromagError(
                f"compensation.band_hz = {band!r}: use [LOW, HIGH] Hz, 0 < LOW < HIGH",
                file=self.source,
            )
        if c["poles"] < 1 or c["trim_s"] < 0:
            raise AeromagError(
                "compensation.poles must be >= 1 and compensation.trim_s >= 0 s", file=self.source
            )
        if not 0.0 <= c["level_guard_alpha"] < 1.0:
            raise AeromagError(
                "compensation.level_guard_alpha: use a p-value in [0, 1) (0: no level guard)",
                file=self.source,
            )
        if not 0.0 <= c["heading_levels_alpha"] < 1.0:
            raise AeromagError(
                "compensation.heading_levels_alpha: use a p-value in [0, 1) (0: no correction)",
                file=self.source,
            )
        a = self.values["audit"]
        if a["baseline"] not in ("tl16", "tl18"):
            raise AeromagError("audit.baseline: use tl18 or tl16", file=self.source)
        if not 0 < a["alpha"] < 1:
            raise AeromagError(
                f"audit.alpha = {a['alpha']}: must be between 0 and 1", file=self.source
            )
        if not 0 <= a["min_gain"] < 1:
            raise AeromagError(
                f"audit.min_gain = {a['min_gain']}: must be in [0, 1)", file=self.source
            )
        if self.values["map"]["cell_m"] < 0:
            raise AeromagError(
                "map.cell_m: must be > 0 m (0: a quarter of the line spacing)", file=self.source
            )
        nav = self.values["navigate"]
        try:
            self.navigation_settings().check()
        except AeromagError as exc:
            raise AeromagError(
                f"navigate: {exc.problem.removeprefix('--')}", file=self.source
            ) from None
        if nav["map"] not in ("anomaly", "anomaly_filtered"):
            raise AeromagError("navigate.map: use anomaly_filtered or anomaly", file=self.source)
        from pipeline.export import check_formats
        from pipeline.maps.enhance import parse_products

        try:
            check_formats(self.values["export"]["formats"])
        except AeromagError as exc:
            raise AeromagError(f"export.formats: {exc.problem}", file=self.source) from None
        e = self.values["enhance"]
        if e["source"] not in ("anomaly", "anomaly_filtered"):
            raise AeromagError("enhance.source: use anomaly_filtered or anomaly", file=self.source)
        try:
            parse_products(e["products"])
        except ValueError as exc:
            raise AeromagError(f"enhance.products: {exc}", file=self.source) from None
        m = self.values["map"]
        if min(m["microlevel_wavelength_m"], m["microlevel_along_m"]) < 0:
            raise AeromagError(
                "map.microlevel_wavelength_m and microlevel_along_m: must be >= 0 m "
                "(0: a multiple of the line spacing)",
                file=self.source,
            )
        if m["microlevel_clip_nT"] <= 0:
            raise AeromagError("map.microlevel_clip_nT: must be > 0 nT", file=self.source)
        if self.values["quality"]["overlap_m"] <= 0:
            raise AeromagError("quality.overlap_m: must be > 0 m", file=self.source)
        try:
            self.fit_settings(c["models"][-1])
            self.map_settings()
            self.despike_settings()
        except ValueError as exc:
            raise AeromagError(str(exc), file=self.source) from None
