"""The grammar every command shares: options, logging, errors, exit statuses.

- ``-h/--help``, ``--version``, ``-v/-vv`` (more log output on stderr) and ``-q`` (errors
  only) on every command;
- the store is always ``--store DIR`` (older spellings stay as hidden aliases);
- a user's mistake is one ``ERROR: ...`` line on stderr, never a traceback: exit status 1
  for an error, 2 for a command line click cannot parse (its own convention), 3 when a
  fit was written but did not reach its tolerance;
- library messages name Python parameters (``sample_spacing_deg``); :func:`user_errors`
  names the command-line option instead (``--sample-spacing``).
"""

from __future__ import annotations

import errno
import functools
import logging
import os
import re
import sys
import warnings

import click

from geoidspline.api import RULES, OptionError, __version__, check_number, pin_mmap_threshold
from geoidspline.errors import GeoidSplineError

CONTEXT = {"help_option_names": ["-h", "--help"]}

#: Library parameter names and the options that set them, for messages.
OPTION_NAMES = {
    "overwrite=True": "--overwrite",
    "resume=True": "--resume",
    "sample_spacing_deg": "--sample-spacing",
    "height_in": "--height-in",
    "blend_width_km": "--blend-width",
    "tolerance_m": "--tolerance",
    "max_level": "--max-level",
    "wait_seconds": "--wait",
    "spacing_deg": "--spacing",
    "max_memory_gb": "--max-memory",
}
_OPTION_PATTERN = re.compile("|".join(re.escape(k) for k in sorted(OPTION_NAMES, key=len, reverse=True)))


def for_the_command_line(message: str) -> str:
    """A library message with its parameter names replaced by the options that set them."""
    return _OPTION_PATTERN.sub(lambda m: OPTION_NAMES[m.group(0)], message)


class _ErrorLines:
    """click's own errors (bad option, missing argument) as ``ERROR:`` lines like every
    other user error, with a pointer to ``--help``."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            result = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.Exit as exc:  # --help, --version
            sys.exit(exc.exit_code)
        except click.ClickException as exc:
            hint = ""
            if isinstance(exc, click.UsageError) and exc.ctx is not None:
                hint = f" (see '{exc.ctx.command_path} --help')"
            click.echo(f"ERROR: {exc.format_message()}{hint}", err=True)
            sys.exit(exc.exit_code)
        except click.Abort:
            click.echo("ERROR: aborted", err=True)
            sys.exit(130)
        try:  # what is still buffered, now, while a fault can still be reported
            sys.stdout.flush()
        except BrokenPipeError:
            _discard_stdout()
        except OSError as exc:
            _discard_stdout()
            click.echo(f"ERROR: cannot write to the standard output: {exc.strerror or exc}", err=True)
            sys.exit(1)
        sys.exit(result if isinstance(result, int) else 0)


class GeoidCommand(_ErrorLines, click.Command):
    """A command of geoidspline."""


class GeoidGroup(_ErrorLines, click.Group):
    """``python -m geoidspline``: the commands under one name, with the same grammar."""


def command(name: str, **kwargs):
    """``click.command`` with the shared class and context settings."""
    return click.command(name=name, cls=GeoidCommand, context_settings={**CONTEXT, **kwargs.pop("context", {})},
                         **kwargs)


class Number(click.ParamType):
    """A numeric option checked by the library's rule for the parameter it sets
    (:func:`geoidspline.options.check_number`): the same range, the same sentence, as
    an ``ERROR: Invalid value for '--h0': ...`` usage line (exit 2)."""

    def __init__(self, rule: str):
        self.rule = rule
        self.name = "integer" if RULES[rule].integer else "float"

    def convert(self, value, param, ctx):
        try:
            return check_number(self.rule, value)
        except OptionError as exc:
            self.fail(f"must be {exc.requirement}, got {value!r}", param, ctx)

    def get_metavar(self, param, ctx=None):
        return "INTEGER" if RULES[self.rule].integer else "FLOAT"


#: ``--region S W N E``: four plain finite numbers (what they make together is
#: :class:`geoidspline.sphere.region.Region`'s to say, exit 1 naming the bound).
REGION = (Number("region_bound_deg"),) * 4


def version_option(func):
    return click.version_option(__version__, "--version", prog_name="geoidspline",
                                message="%(prog)s %(version)s")(func)


def band_options(func):
    """Add ``--band`` and ``--variable``: which band or variable of a SOURCE with several."""
    func = click.option("--variable", default=None, metavar="NAME",
                        help="The variable of a netCDF SOURCE with several 2-D candidates; required for such a file.")(func)
    return click.option("--band", type=click.IntRange(min=1), default=None, metavar="N",
                        help="The band of a GeoTIFF SOURCE with several (1-based); required for such a file.")(func)


def verbosity_options(func):
    """Add ``--version``, ``-v/--verbose`` (repeatable) and ``-q/--quiet``, and set up logging."""

    @click.option("-v", "--verbose", count=True, help="More log output on stderr (-vv for debug).")
    @click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr; no progress bar.")
    @functools.wraps(func)
    def wrapper(*args, verbose, quiet, **kwargs):
        level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
        logging.basicConfig(level=level, stream=sys.stderr, format="%(levelname)s: %(message)s", force=True)
        warnings.showwarning = _warning_as_log_line
        # a command owns its process: freed arrays go back to the system (the library
        # itself leaves the process's allocator alone; see geoidspline._memory)
        pin_mmap_threshold()
        return func(*args, quiet=quiet, verbose=verbose, **kwargs)

    return version_option(wrapper)


def _warning_as_log_line(message, category, filename, lineno, file=None, line=None):
    """geoidspline's own warnings (a tide system corrected from C̄20, say) as one
    ``WARNING: ...`` line through logging, like every other statement on stderr (``-q``
    silences it); the library also records them in the provenance notes. Other
    packages' warnings keep Python's own format."""
    if issubclass(category, Warning) and category.__module__.startswith("geoidspline"):
        logging.getLogger("geoidspline").warning("%s", message)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


_python_showwarning = warnings.showwarning


def store_options(help_text: str, *, positional: bool = False, aliases=()):
    """``--store DIR`` (and, for old scripts, a positional STORE or hidden alias options)
    merged into the keyword argument ``store_path``."""

    def decorate(func):
        @functools.wraps(func)
        def wrapper(*args, store_path, store_positional=None, **kwargs):
            given = [v for v in [store_path, store_positional] + [kwargs.pop(f"store_alias_{i}") for i in
                                                                  range(len(aliases))] if v is not None]
            if len(set(given)) > 1:
                raise click.UsageError(f"the store is given twice ({' and '.join(map(str, given))})")
            return func(*args, store_path=given[0] if given else None, **kwargs)

        wrapped = click.option("--store", "store_path", type=click.Path(), default=None, metavar="DIR",
                               help=help_text)(wrapper)
        for i, alias in enumerate(aliases):
            wrapped = click.option(alias, f"store_alias_{i}", type=click.Path(), default=None, hidden=True)(wrapped)
        if positional:
            wrapped = click.argument("store_positional", required=False, metavar="[STORE]")(wrapped)
        return wrapped

    return decorate


class OutputError(GeoidSplineError):
    """The standard output cannot be written (a full disk, a quota, an I/O error)."""


class _Output:
    """The standard output for results: every write flushed, and a fault writing it
    turned into :class:`OutputError` (a closed pipe stays ``BrokenPipeError``)."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text):
        try:
            self.stream.write(text)
            self.stream.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise OutputError(f"cannot write to the standard output: {exc.strerror or exc}") from None


def output_stream() -> _Output:
    """Where a command writes its results (the current ``sys.stdout``)."""
    return _Output(sys.stdout)


def echo(message="") -> None:
    """``click.echo`` of one line of results to the standard output, with the faults of
    :class:`_Output`."""
    output_stream().write(f"{message}\n")


def _discard_stdout():
    """Point the standard output at /dev/null, so that the interpreter's last flush of
    what is still buffered cannot fail again (no "Exception ignored" after our message)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return  # not a real file (tests): nothing is flushed at exit
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


def user_errors(func):
    """Report GeoidSplineError and file-system faults as one ``ERROR: ...`` line, exit 1.

    A closed pipe on the standard output (``| head``) ends the command quietly, exit 0.
    """

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except OutputError as exc:
            _discard_stdout()
            click.echo(f"ERROR: {exc}", err=True)
            sys.exit(1)
        except GeoidSplineError as exc:
            click.echo(f"ERROR: {for_the_command_line(str(exc))}", err=True)
            sys.exit(1)
        except OSError as exc:
            if exc.errno == errno.EPIPE:  # the reader went away (| head): not an error of ours
                _discard_stdout()
                sys.exit(0)
            where = f"{exc.filename}: " if exc.filename else ""
            click.echo(f"ERROR: {where}{exc.strerror or exc}", err=True)
            sys.exit(1)
        except MemoryError:
            click.echo("ERROR: out of memory (try a smaller region or batch)", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("ERROR: interrupted", err=True)
            sys.exit(130)

    return wrapper
