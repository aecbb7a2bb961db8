"""Deliverables from a processed recording: map grids and line data in the formats other
software reads (GeoTIFF, CF netCDF, CSV, Geosoft XYZ, MagNav.jl HDF5).

Everything is read back from the processed MCAP (:mod:`pipeline.export.source`): the grids'
georeference is its ``/map/frame`` channel, the line data its ``/map/lines``.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import AeromagError

FORMATS = ("geotiff", "netcdf", "csv", "xyz", "magnav")
NOT_MAGNAV = ("/map/uncertainty", "/map/navigability")  # grids that are not anomaly maps

__all__ = ["FORMATS", "check_formats", "export_recording"]


def check_formats(formats, source: str | None = None) -> list[str]:
    """The formats, checked against :data:`FORMATS` (order kept, duplicates dropped).

    Raises
    ------
    AeromagError
        An unknown format (naming ``source``: the configuration file or the command line).
    """
    out: list[str] = []
    for f in formats:
        f = str(f).strip().lower()
        if f not in FORMATS:
            raise AeromagError(
                f"unknown export format {f!r}: use some of {', '.join(FORMATS)}", file=source
            )
        if f not in out:
            out.append(f)
    return out


def export_recording(
    recording: str | Path, out_dir: str | Path, formats=None
) -> dict[str, list[str]]:
    """Write every map channel of a processed recording (and its levelled line data, for
    ``csv`` and ``xyz``) into ``out_dir``, each file atomically.

    Files (``STEM``: the recording's name without ``.processed.mcap``):
    ``STEM.<grid>.tif`` per grid channel (``anomaly``, ``anomaly_filtered``, ``uncertainty``,
    ``rtp`` ...), ``STEM.maps.nc``, ``STEM.lines.csv``, ``STEM.lines.xyz``,
    ``STEM.<grid>.magnav.h5`` (every grid but ``uncertainty`` and ``navigability``).

    ``formats``: some of :data:`FORMATS`; by default the configuration's ``export.formats``.

    Returns
    -------
    dict
        Format -> the paths written.

    Raises
    ------
    AeromagError
        No map channel, no georeference or no line data in the recording, or an unknown format.
    """
    from pipeline.defaults import default_value
    from pipeline.export.grid_files import write_geotiff, write_netcdf
    from pipeline.export.lines import line_table, write_csv, write_xyz
    from pipeline.export.magnav import write_magnav_h5
    from pipeline.export.source import read_map_products

    formats = check_formats(default_value("export", "formats") if formats is None else formats)
    out = Path(out_dir)
    mp = read_map_products(recording, lines=bool({"csv", "xyz"} & set(formats)))
    stem = mp.stem
    written: dict[str, list[str]] = {}

    def put(fmt: str, path: Path) -> None:
        written.setdefault(fmt, []).append(str(path))

    try:
        if "geotiff" in formats:
            for g in mp.grids:
                put("geotiff", write_geotiff(out / f"{stem}.{g.name}.tif", g, mp.frame))
        if "netcdf" in formats:
            put("netcdf", write_netcdf(out / f"{stem}.maps.nc", mp.grids, mp.frame))
        if "magnav" in formats:
            # not the error and navigability grids: MagNav's map file has no such field, and
            # either read as a map would be navigated on
            for g in (g for g in mp.grids if g.topic not in NOT_MAGNAV):
                put("magnav", write_magnav_h5(out / f"{stem}.{g.name}.magnav.h5", g, mp.frame))
        if {"csv", "xyz"} & set(formats):
            table = line_table(mp.lines, mp.frame)
            if "csv" in formats:
                put("csv", write_csv(out / f"{stem}.lines.csv", table))
            if "xyz" in formats:
                put("xyz", write_xyz(out / f"{stem}.lines.xyz", table, mp.frame, stem))
    except ValueError as exc:
        raise AeromagError(f"export: {exc}", file=recording) from None
    except OSError as exc:
        raise AeromagError(f"cannot write the export ({exc})", file=out) from None
    return written
