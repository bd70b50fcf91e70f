"""geoid-export: a tile store sampled on a latitude/longitude grid, as GTX, netCDF or GeoTIFF."""

from __future__ import annotations

import json
import logging
import time

import click

from geoidspline.api import TIDE_SYSTEM_NAMES

from ._common import REGION, Number, command, echo, store_options, user_errors, verbosity_options

log = logging.getLogger("geoidspline.cli")


@command("export")
@store_options("Tile store directory (may also be given as the argument STORE).", positional=True)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="Grid file to write: FILE.gtx (PROJ GTX), FILE.nc (CF netCDF) or FILE.tif (GeoTIFF, needs rasterio).")
@click.option("--spacing", type=Number("spacing_deg"), required=True, help="Node spacing in degrees (latitude and longitude).")
@click.option("--region", nargs=4, type=REGION, metavar="S W N E", default=None,
              help="Region in degrees: south west north east [default: the store's region].")
@click.option("--tide-system", type=click.Choice(TIDE_SYSTEM_NAMES), default=None,
              help="Tide system of the grid written: the store's values are converted to it [default: the store's].")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@verbosity_options
@user_errors
def main(store_path, out, spacing, region, tide_system, as_json, quiet, verbose):
    """Evaluate the tile store at --store every --spacing degrees and write the grid to --out.

    Nodes run from the south edge of the region northward and from its west edge
    eastward, up to the last node at or before the north/east edge (a region all around
    the globe gives a periodic grid without a repeated 360° column). The region must lie
    inside the store's. A GTX works with PROJ's vgridshift, which interpolates it
    bilinearly: choose the spacing for the accuracy you need.
    """
    import geoidspline

    if store_path is None:
        raise click.UsageError("give --store DIR, the store to export")
    from geoidspline.api import Region, export_grid

    store = geoidspline.open_store(store_path)
    started = time.perf_counter()
    grid = export_grid(store, out, spacing, Region.from_bounds(*region) if region else None, tide_system=tide_system)
    nlat, nlon = grid.shape
    summary = {
        "file": str(out),
        "store": str(store_path),
        "spacing_deg": float(spacing),
        "rows": int(nlat),
        "columns": int(nlon),
        "south": float(grid.latitude[0]),
        "north": float(grid.latitude[-1]),
        "west": float(grid.longitude[0]),
        "east": float(grid.longitude[-1]),
        "tide_system": grid.provenance.tide_system,
        "seconds": round(time.perf_counter() - started, 3),
    }
    if as_json:
        echo(json.dumps(summary, indent=1))
        return
    echo(f"wrote {out}: {nlat} x {nlon} nodes every {spacing:g} degrees, "
               f"latitude {summary['south']:g}..{summary['north']:g}, "
               f"longitude {summary['west']:g}..{summary['east']:g}"
               + (f", tide system {grid.provenance.tide_system}" if tide_system else ""))


if __name__ == "__main__":  # pragma: no cover
    main()
