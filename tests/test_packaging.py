"""Packaging: README commands, .ci/run, Dockerfile, requirements.lock, installed import names.

All fast and offline except ``test_replay_docker`` (network, ~2 min), which runs only
with ``pytest --slow``.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    tomllib = pytest.importorskip("tomli")

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
DOCKERFILE = REPO / "Dockerfile"
LOCK = REPO / "requirements.lock"
CI_RUN = REPO / ".ci" / "run"
PYPROJECT = REPO / "pyproject.toml"


def normalise(name: str) -> str:
    """PEP 503 normalised distribution name."""
    return re.sub(r"[-_.]+", "-", name).lower()


def readme_commands() -> list[str]:
    """The commands of the README's first two ```sh blocks (before the first section)."""
    text = README.read_text(encoding="utf-8")
    head = text.split("\n## ", 1)[0]
    blocks = re.findall(r"```sh\n(.*?)```", head, flags=re.S)
    commands = [ln.strip() for block in blocks for ln in block.splitlines() if ln.strip()]
    return commands


def chain(command: str) -> list[list[str]]:
    """A `a && b && c` command line as a list of argument lists."""
    words = shlex.split(command)
    parts, current = [], []
    for w in words:
        if w == "&&":
            parts.append(current)
            current = []
        else:
            current.append(w)
    parts.append(current)
    return parts


def pip_install_args(argv: list[str]) -> list[str] | None:
    """The arguments after `install` if argv is a pip install (pip, .venv/bin/pip, python -m pip)."""
    if len(argv) >= 2 and Path(argv[0]).name in ("pip", "pip3") and argv[1] == "install":
        return argv[2:]
    if len(argv) >= 4 and Path(argv[0]).name.startswith("python") and argv[1:4] == ["-m", "pip", "install"]:
        return argv[4:]
    return None


def package_install(args: list[str]) -> list[str] | None:
    """A pip install of the project itself (from `.`), without output-only flags."""
    if "-r" in args or "--requirement" in args:
        return None
    targets = [a for a in args if not a.startswith("-")]
    if not any(t == "." or t.startswith(".[") for t in targets):
        return None
    return [a for a in args if a not in ("-q", "--quiet", "--no-cache-dir")]


def dockerfile_instructions() -> list[tuple[str, str]]:
    out, buf = [], ""
    for raw in DOCKERFILE.read_text(encoding="utf-8").splitlines():
        if not buf and (not raw.strip() or raw.lstrip().startswith("#")):
            continue
        if raw.endswith("\\"):
            buf += raw[:-1] + " "
            continue
        line = (buf + raw).strip()
        buf = ""
        instr, _, rest = line.partition(" ")
        out.append((instr.upper(), rest.strip()))
    return out


def docker_pip_installs() -> list[list[str]]:
    installs = []
    for instr, rest in dockerfile_instructions():
        if instr == "RUN":
            for argv in chain(rest):
                args = pip_install_args(argv)
                if args is not None:
                    installs.append(args)
    return installs


# -- README and .ci/run -----------------------------------------------------------------


def test_readme_starts_with_exactly_two_commands():
    commands = readme_commands()
    assert len(commands) == 2, commands
    setup, tests = commands
    assert "proj-data" in setup and "geoid-fit egm96-15" in setup and "geoid-query" in setup
    assert "pytest" in tests


def test_readme_setup_command_fits_and_queries_with_negative_coordinates():
    setup = chain(readme_commands()[0])
    fit = next(argv for argv in setup if Path(argv[0]).name == "geoid-fit")
    query = next(argv for argv in setup if Path(argv[0]).name == "geoid-query")
    region = fit[fit.index("--region") + 1:fit.index("--region") + 5]
    assert [float(v) for v in region] == [-60, -90, 15, -30]
    store = fit[fit.index("--store") + 1]
    assert query[query.index("--store") + 1] == store
    assert [float(v) for v in query[-2:]] == [-33.45, -70.66]


def test_readme_setup_installs_a_c_compiler_before_the_package_and_nothing_after():
    """pip builds the C kernels (a compiler, no Python headers), and then nothing is left to
    compile: the fit follows the install directly."""
    setup = chain(readme_commands()[0])
    names = [Path(argv[0]).name for argv in setup]
    apt = next(i for i, argv in enumerate(setup) if argv[:2] == ["apt-get", "install"])
    assert "gcc" in setup[apt]
    install = max(i for i, argv in enumerate(setup)
                  if (args := pip_install_args(argv)) is not None and package_install(args) is not None)
    assert apt < install and names[install + 1] == "geoid-fit", names
    assert not any(name.startswith("geoid-warmup") for name in names)


def test_ci_run_runs_the_readme_test_command():
    ci_lines = [ln.strip() for ln in CI_RUN.read_text(encoding="utf-8").splitlines()
                if ln.strip() and not ln.lstrip().startswith("#")]
    commands = [ln for ln in ci_lines if not re.match(r"(set|cd|export)\b", ln)]
    assert commands == [readme_commands()[1]], commands
    assert CI_RUN.read_text().startswith("#!/usr/bin/env bash")
    assert "set -euo pipefail" in ci_lines
    assert os.access(CI_RUN, os.X_OK)


# -- Dockerfile ---------------------------------------------------------------------------


def dockerfile_stages() -> list[list[tuple[str, str]]]:
    """The Dockerfile's instructions, one list per stage (each starting with its FROM)."""
    stages = []
    for instr, rest in dockerfile_instructions():
        if instr == "FROM":
            stages.append([])
        stages[-1].append((instr, rest))
    return stages


def runs_of(stage) -> list[list[str]]:
    return [argv for instr, rest in stage if instr == "RUN" for argv in chain(rest)]


def test_dockerfile_builds_the_readme_package_as_a_wheel_and_installs_it_with_the_plot_extra():
    readme_installs = [package_install(args) for argv in chain(readme_commands()[0])
                       if (args := pip_install_args(argv)) is not None]
    assert [a for a in readme_installs if a is not None] == [["."]], readme_installs
    build, final = dockerfile_stages()
    wheel = [argv for argv in runs_of(build) if argv[:2] == ["pip", "wheel"]]
    assert len(wheel) == 1 and wheel[0][-1] == "." and "--no-deps" in wheel[0], wheel
    wheel_dir = wheel[0][wheel[0].index("--wheel-dir") + 1]
    assert any(instr == "COPY" and rest.split() == [f"--from={build[0][1].split()[-1]}", wheel_dir, wheel_dir]
               for instr, rest in final)
    installs = [pip_install_args(argv) for argv in runs_of(final) if pip_install_args(argv) is not None]
    # geoid-plot must work in the image; --no-index: the lock must already hold every dependency
    assert installs[-1] == ["--no-index", "--find-links", wheel_dir, "geoidspline[plot]"], installs


def test_dockerfile_checks_that_the_image_holds_exactly_the_lock():
    runs = [argv for instr, rest in dockerfile_instructions() if instr == "RUN" for argv in chain(rest)]
    freeze = next(argv for argv in runs if argv[:2] == ["pip", "freeze"])
    assert freeze[2:4] == ["--exclude", "geoidspline"] and "|" in freeze and "requirements.lock" in freeze
    assert ["pip", "check"] in runs


def test_dockerignore_admits_only_what_the_image_copies():
    patterns = [ln.strip() for ln in (REPO / ".dockerignore").read_text(encoding="utf-8").splitlines()
                if ln.strip() and not ln.lstrip().startswith("#")]
    assert patterns[0] == "*"  # everything out (.venv, .git, caches, stores), then the sources back in
    admitted = {p[1:] for p in patterns if p.startswith("!")}
    copies = [shlex.split(rest)[:-1] for instr, rest in dockerfile_instructions()
              if instr == "COPY" and not rest.startswith("--from=")]
    assert admitted == {src.rstrip("/") for srcs in copies for src in srcs}
    assert {"**/__pycache__", "**/*.pyc"} <= set(patterns)


def test_dockerfile_installs_the_lock_before_the_package():
    build, final = dockerfile_stages()
    installs = [pip_install_args(argv) for argv in runs_of(final) if pip_install_args(argv) is not None]
    assert installs[0] == ["-r", "requirements.lock"], installs
    assert any("requirements.lock" in rest.split() for instr, rest in final if instr == "COPY")
    # everything `pip wheel .` needs is copied into the build stage
    copied = {w for instr, rest in build if instr == "COPY" for w in shlex.split(rest)[:-1]}
    assert {"pyproject.toml", "README.md", "geoidspline", "cli", "grids"} <= copied, copied


def test_dockerfile_compiles_in_the_build_stage_only():
    """gcc builds the kernels in the first stage; the image itself holds no compiler and
    compiles nothing at run time (no numba, no warm-up step)."""
    build, final = dockerfile_stages()
    apt_build = [argv for argv in runs_of(build) if argv[:2] == ["apt-get", "install"]]
    assert len(apt_build) == 1 and "gcc" in apt_build[0]
    assert not any("gcc" in argv for argv in runs_of(final) if argv[:2] == ["apt-get", "install"])
    text = DOCKERFILE.read_text(encoding="utf-8")
    assert "geoid-warmup" not in text and "NUMBA" not in text


def test_dockerfile_base_image_is_pinned():
    bases = [stage[0][1].split()[0] for stage in dockerfile_stages()]
    assert len(bases) == 2 and bases[0] == bases[1], bases
    assert re.fullmatch(r"python:3\.11\.\d+-slim-[a-z]+(@sha256:[0-9a-f]{64})?", bases[0]), bases


def test_dockerfile_installs_proj_data_only():
    apt = [argv for argv in runs_of(dockerfile_stages()[-1]) if argv[:2] == ["apt-get", "install"]]
    assert len(apt) == 1
    assert "--no-install-recommends" in apt[0]
    assert [a for a in apt[0][2:] if not a.startswith("-")] == ["proj-data"]


def test_dockerfile_runs_as_non_root_in_data():
    instructions = dockerfile_instructions()
    users = [rest for instr, rest in instructions if instr == "USER"]
    assert users and users[-1].split(":")[0] not in ("root", "0")
    last_user = max(i for i, (instr, _) in enumerate(instructions) if instr == "USER")
    assert not any(instr == "RUN" for instr, _ in instructions[last_user:]), "RUN after the final USER"
    workdirs = [rest for instr, rest in instructions if instr == "WORKDIR"]
    assert workdirs[-1] == "/data"
    assert any(instr == "VOLUME" and "/data" in rest for instr, rest in instructions)
    assert not any(instr == "ENTRYPOINT" for instr, _ in instructions)
    cmd = [rest for instr, rest in instructions if instr == "CMD"]
    assert cmd == ['["geoid-info", "--help"]']


# -- requirements.lock --------------------------------------------------------------------


def lock_entries() -> dict[str, str]:
    entries = {}
    for line in LOCK.read_text(encoding="utf-8").splitlines():
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([0-9][A-Za-z0-9.+!_-]*)", line)
        assert m, f"requirements.lock line is not name==version: {line!r}"
        entries[normalise(m.group(1))] = m.group(2)
    return entries


def test_lock_lines_are_exact_pins():
    entries = lock_entries()
    assert len(entries) == len(LOCK.read_text().splitlines())  # no duplicates, no blank lines


def test_lock_covers_every_runtime_dependency():
    from packaging.requirements import Requirement

    with open(PYPROJECT, "rb") as fh:
        project = tomllib.load(fh)["project"]
    entries = lock_entries()
    for spec in project["dependencies"]:
        req = Requirement(spec)
        name = normalise(req.name)
        assert name in entries, f"{req.name} (pyproject.toml) is not pinned in requirements.lock"
        assert req.specifier.contains(entries[name], prereleases=True), (
            f"requirements.lock pins {req.name}=={entries[name]}, outside pyproject's {req.specifier}"
        )


def _closure(requirement: str, extras=()) -> set[str]:
    """Normalised names of the installed distributions ``requirement`` (with ``extras``) needs."""
    from importlib.metadata import PackageNotFoundError, distribution

    from packaging.requirements import Requirement

    seen, todo = set(), [(requirement, tuple(extras))]
    while todo:
        name, wanted = todo.pop()
        try:
            dist = distribution(name)
        except PackageNotFoundError:
            pytest.skip(f"{name} is not installed here: the closure cannot be derived")
        for spec in dist.requires or []:
            req = Requirement(spec)
            env = {"extra": ""}
            if req.marker is not None and not any(req.marker.evaluate({"extra": e}) for e in wanted or ("",)):
                continue
            if req.marker is not None and not wanted and not req.marker.evaluate(env):
                continue
            key = normalise(req.name)
            if key not in seen:
                seen.add(key)
                todo.append((req.name, tuple(req.extras)))
    return seen


def test_lock_is_exactly_the_closure_of_the_plot_extra():
    """No pin of a package the image does not need (numcodecs was one), none missing."""
    from importlib.metadata import version

    entries = lock_entries()
    closure = _closure("geoidspline", ["plot"])
    differ = sorted(f"{n} {version(n)} (lock {entries[n]})" for n in closure & set(entries) if version(n) != entries[n])
    if differ:  # another version may need other packages: this environment is not the image's
        pytest.skip("installed versions differ from requirements.lock: " + ", ".join(differ))
    assert set(entries) == closure


# -- the installed package ----------------------------------------------------------------


def test_installed_package_exposes_cli_and_grids_inside_geoidspline(tmp_path):
    # from a directory without the sources: the repository root on sys.path would
    # make the top-level cli/ and grids/ directories importable and hide a leak
    code = (
        "import importlib.util, importlib.resources, geoidspline.cli, geoidspline.grids;"
        "print(importlib.util.find_spec('cli'), importlib.util.find_spec('grids'));"
        "print(importlib.resources.files('geoidspline.grids').joinpath('catalogue.toml').is_file())"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["None", "None", "True"], proc.stdout


def test_setuptools_maps_cli_and_grids_into_geoidspline():
    with open(PYPROJECT, "rb") as fh:
        tool = tomllib.load(fh)["tool"]["setuptools"]
    packages = tool["packages"]
    assert "cli" not in packages and "grids" not in packages
    assert tool["package-dir"]["geoidspline.cli"] == "cli"
    assert tool["package-dir"]["geoidspline.grids"] == "grids"
    for package in packages:  # every listed package has its directory (longest mapped prefix)
        parts = package.split(".")
        n = max(i for i in range(len(parts) + 1) if i == 0 or ".".join(parts[:i]) in tool["package-dir"])
        base = REPO / tool["package-dir"][".".join(parts[:n])] if n else REPO
        assert (base.joinpath(*parts[n:]) / "__init__.py").is_file(), package


def test_every_package_directory_is_installed():
    """A new package under geoidspline/ must be listed, or a plain install would lack it."""
    with open(PYPROJECT, "rb") as fh:
        packages = set(tomllib.load(fh)["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "geoidspline").rglob("__init__.py")}
    assert found <= packages, sorted(found - packages)


@pytest.mark.slow  # needs network; installs, compiles the kernels: ~5-10 min
def test_replay_docker(tmp_path):
    """The Dockerfile's pip install steps work in a fresh venv and give working commands."""
    env = dict(os.environ, TMPDIR=str(tmp_path))
    proc = subprocess.run(["bash", str(REPO / "benchmarks" / "replay_docker.sh")], capture_output=True, text=True,
                          timeout=1800, env=env, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "replay ok:" in proc.stdout


def test_python_m_geoidspline_runs_from_the_checkout_root():
    """From the repository root the source tree is imported, not the install: cli/ must
    still be found as geoidspline.cli."""
    done = subprocess.run([sys.executable, "-m", "geoidspline", "--help"], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "fit" in done.stdout and "query" in done.stdout


def test_the_checkout_finder_maps_cli_and_grids_to_the_top_level_folders():
    import geoidspline

    for name in ("cli", "grids"):
        spec = geoidspline._CheckoutPackages.find_spec(f"geoidspline.{name}")
        assert Path(spec.origin) == REPO / name / "__init__.py"
    assert geoidspline._CheckoutPackages.find_spec("geoidspline.store") is None
