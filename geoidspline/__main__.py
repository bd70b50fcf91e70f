"""``python -m geoidspline fit|query|info|export|plot ...``: the commands under one name."""

import click

from geoidspline.cli import export, fit, info, plot, query


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """geoidspline: geoid undulations as C² ambient B-spline tiles."""


main.add_command(fit.main, "fit")
main.add_command(query.main, "query")
main.add_command(info.main, "info")
main.add_command(export.main, "export")
main.add_command(plot.main, "plot")

if __name__ == "__main__":
    main()
