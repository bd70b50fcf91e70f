# geoidspline: fit geoid grids into ambient B-spline tile stores, query them.
#
# Build (from the repository root):
#   docker build -t geoidspline .
# Fit PROJ's EGM96 15' grid (shipped in the image by Debian's proj-data) over the Andes,
# writing the store into the current directory, then query it:
#   docker run --rm -v "$PWD:/data" geoidspline geoid-fit egm96-15 --region -60 -90 15 -30 --tolerance 0.5 --store /data/store
#   docker run --rm -v "$PWD:/data" geoidspline geoid-query --store /data/store -33.45 -70.66
#   docker run --rm -v "$PWD:/data" geoidspline geoid-info --store /data/store
# The container runs as the non-root user "geoid" (uid 1000); if your uid differs and the
# mounted directory is not writable for uid 1000, add --user "$(id -u):$(id -g)".
#
# requirements.lock is what this image installs (`pip freeze --exclude geoidspline` in the
# built image: the closure of geoidspline[plot]); the build fails if `pip install` would
# bring anything else. The base image is pinned to the patch release it was frozen on.
# .dockerignore keeps the build context to the files copied below.
FROM python:3.11.7-slim-bookworm

# egm96_15.gtx (and PROJ's other grids) in /usr/share/proj, where the catalogue looks
RUN apt-get update \
 && apt-get install -y --no-install-recommends proj-data \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 1000 --shell /usr/sbin/nologin geoid \
 && mkdir -p /data /var/cache/numba \
 && chown geoid:geoid /data

ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/numba

WORKDIR /opt/geoidspline
COPY requirements.lock ./
RUN pip install -r requirements.lock
COPY pyproject.toml README.md ./
COPY geoidspline ./geoidspline
COPY cli ./cli
COPY grids ./grids
# README.md's set-up command plus the plot extra, so geoid-plot works in the image
# (non-editable; cli/ and grids/ install as geoidspline.cli and geoidspline.grids). Then
# the installed set must be the lock exactly, and consistent.
RUN pip install '.[plot]' \
 && pip freeze --exclude geoidspline | diff -u requirements.lock - \
 && pip check

# Compile every numba kernel into the image's cache (NUMBA_CACHE_DIR), the README's set-up
# step: a container's first fit or query loads them instead of compiling for a minute or
# more. The second run checks, in a fresh process, that every kernel now loads from the
# cache. A host whose CPU model differs from the build machine's recompiles once (numba
# keys its cache on the CPU); the cache stays writable for any uid. (The console script,
# not `python -m` here: that would import the sources in this directory instead of the
# installed package, and numba keys its cache on the source file's path.)
RUN geoid-warmup -q \
 && geoid-warmup --check -q \
 && chmod -R a+rwX /var/cache/numba

USER geoid
WORKDIR /data
VOLUME ["/data"]
CMD ["geoid-info", "--help"]
