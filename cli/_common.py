"""Shared plumbing of the commands: logging options and error handling."""

from __future__ import annotations

import functools
import logging
import sys

import click

from geoidspline.errors import GeoidSplineError


def verbosity_options(func):
    """Add ``-v/--verbose`` (repeatable) and ``-q/--quiet``, and set up logging."""

    @click.option("-v", "--verbose", count=True, help="More log output on stderr (-vv for debug).")
    @click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr; no progress bar.")
    @functools.wraps(func)
    def wrapper(*args, verbose, quiet, **kwargs):
        level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
        logging.basicConfig(level=level, stream=sys.stderr, format="%(levelname)s: %(message)s", force=True)
        return func(*args, quiet=quiet, **kwargs)

    return wrapper


def user_errors(func):
    """Report GeoidSplineError (and unreadable files) as ``ERROR: ...`` and exit 1."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except GeoidSplineError as exc:
            click.echo(f"ERROR: {exc}", err=True)
            sys.exit(1)
        except (FileNotFoundError, PermissionError, IsADirectoryError) as exc:
            click.echo(f"ERROR: {exc.filename}: {exc.strerror}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("ERROR: interrupted", err=True)
            sys.exit(130)

    return wrapper
