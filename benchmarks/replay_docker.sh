#!/usr/bin/env bash
# Replay the Docker image's Python install without Docker:
#
#   bash benchmarks/replay_docker.sh [DOCKERFILE]
#
# Reads the Dockerfile (default: the repository's), follows its WORKDIR and COPY
# instructions into a scratch "image root" (one root for both stages: the build stage's
# paths, /opt/geoidspline and /wheels, are where the final stage's `COPY --from` puts
# them) and replays every `RUN pip wheel ...` and `RUN pip install ...` line there with a
# fresh venv's pip (python3 -m venv $TMP/venv), so the COPY set and the pinned
# requirements.lock are checked too (with the image's `pip freeze | diff` against the lock
# and `pip check`). The apt-get lines are not replayed: the host needs gcc. Then runs the
# image's commands (geoid-fit --help, geoid-query --help, geoid-info --help) from that venv.
# Needs network access to the package index (or a local mirror in pip's configuration);
# takes a few minutes. Exit status 0 when everything worked.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/.." && pwd)"
dockerfile="${1:-$repo/Dockerfile}"
context="$(cd "$(dirname "$dockerfile")" && pwd)"

TMP="$(mktemp -d "${TMPDIR:-/tmp}/replay_docker.XXXXXX")"
trap 'rm -rf "$TMP"' EXIT
root="$TMP/root"
mkdir -p "$root"

python3 -m venv "$TMP/venv"
venv_bin="$TMP/venv/bin"

# One step per line: "copy<TAB>SRC<TAB>DEST" or "run<TAB>CWD<TAB>ARGS..." (paths in the image).
steps="$TMP/steps"
python3 - "$dockerfile" >"$steps" <<'PY'
import posixpath
import shlex
import sys

lines, buf = [], ""
for raw in open(sys.argv[1], encoding="utf-8"):
    line = raw.rstrip("\n")
    if not buf and (not line.strip() or line.lstrip().startswith("#")):
        continue
    if line.endswith("\\"):
        buf += line[:-1] + " "
        continue
    lines.append(buf + line)
    buf = ""
workdir = "/"
found = 0
for line in lines:
    instr, _, rest = line.strip().partition(" ")
    instr = instr.upper()
    if instr == "WORKDIR":
        workdir = posixpath.normpath(posixpath.join(workdir, rest.strip()))
    elif instr == "COPY":
        if rest.strip().startswith("--from="):
            continue  # from the build stage, already at its place in the one root
        args = [a for a in shlex.split(rest) if not a.startswith("--")]
        *srcs, dest = args
        dest_abs = posixpath.join(workdir, dest)
        for src in srcs:
            target = dest_abs
            if dest.endswith("/") or len(srcs) > 1:
                target = posixpath.join(dest_abs, posixpath.basename(src.rstrip("/")))
            print(f"copy\t{src}\t{posixpath.normpath(target)}")
    elif instr == "RUN":
        words = shlex.split(rest)
        # each command of a `a && b` chain: pip wheel, pip install, the lock check (pip
        # freeze ... | diff, pip check); rm -rf of a path in the root
        part = []
        for w in words + ["&&"]:
            if w != "&&":
                part.append(w)
                continue
            if part[:2] in (["pip", "install"], ["pip", "wheel"]):
                found += 1
                print("run\t" + workdir + "\t" + "\t".join(part[1:]))
            elif part[:2] == ["pip", "freeze"] and "|" in part:
                bar = part.index("|")
                print("freeze\t" + workdir + "\t" + "\t".join(part[2:bar]) + "\t|\t" + "\t".join(part[bar + 1:]))
            elif part == ["pip", "check"]:
                print("check\t" + workdir + "\t")
            part = []
if not found:
    sys.exit(f"{sys.argv[1]}: no 'RUN pip install' line")
PY

while IFS=$'\t' read -r kind a b rest; do
  case "$kind" in
    copy)
      src="$context/$a"
      dest="$root$b"
      if [ -d "$src" ]; then
        mkdir -p "$dest"
        # the directory's contents, without caches and build leftovers
        (cd "$src" && tar --exclude='__pycache__' --exclude='*.egg-info' --exclude='build' -cf - .) | (cd "$dest" && tar -xf -)
      else
        mkdir -p "$(dirname "$dest")"
        cp "$src" "$dest"
      fi
      ;;
    run)
      mkdir -p "$root$a"
      args=()
      [ -n "$b" ] && args+=("$b")
      if [ -n "${rest:-}" ]; then
        IFS=$'\t' read -r -a more <<<"$rest"
        args+=("${more[@]}")
      fi
      # paths of the image (the wheel directory) live under the scratch root
      for i in "${!args[@]}"; do
        case "${args[$i]}" in /*) args[$i]="$root${args[$i]}" ;; esac
      done
      echo "+ (cd $a) pip ${args[*]}" >&2
      (cd "$root$a" && PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 "$venv_bin/pip" -q "${args[@]}")
      ;;
    freeze)
      # `pip freeze ARGS | CMD...`: the installed set against the lock (CMD reads stdin)
      IFS=$'\t' read -r -a all <<<"$b${rest:+$'\t'$rest}"
      bar=0; while [ "${all[$bar]}" != "|" ]; do bar=$((bar + 1)); done
      echo "+ (cd $a) pip freeze ${all[*]:0:$bar} | ${all[*]:$((bar + 1))}" >&2
      (cd "$root$a" && "$venv_bin/pip" freeze "${all[@]:0:$bar}" | "${all[@]:$((bar + 1))}")
      ;;
    check)
      echo "+ pip check" >&2
      "$venv_bin/pip" check
      ;;
  esac
done <"$steps"

# the image's commands, run from a directory without the sources
cd "$TMP"
for cmd in geoid-fit geoid-query geoid-info; do
  echo "+ $cmd --help" >&2
  "$venv_bin/$cmd" --help >/dev/null
done
"$venv_bin/python" -c "import geoidspline, geoidspline.cli, geoidspline.grids, importlib.util; \
assert importlib.util.find_spec('cli') is None and importlib.util.find_spec('grids') is None, 'top-level cli/grids installed'; \
assert geoidspline.__file__.startswith('$TMP/venv/'), geoidspline.__file__; print('replay ok:', geoidspline.__file__)"
