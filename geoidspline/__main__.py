"""``python -m geoidspline fit|update|query|info|export|plot ...``: the commands under one name."""

import click

from geoidspline.cli import export, fit, info, plot, query, update
from geoidspline.cli._common import CONTEXT, GeoidGroup, version_option


@click.group(cls=GeoidGroup, context_settings=CONTEXT)
@version_option
def main():
    """geoidspline: geoid undulations as C² ambient B-spline tiles."""


for _module in (fit, update, query, info, export, plot):
    main.add_command(_module.main)

if __name__ == "__main__":
    main()
