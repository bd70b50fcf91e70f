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
# built image: the closure of geoidspline[plot]); the build fails if the package's install
# would bring anything else. The base image is pinned to the patch release it was frozen on.
# .dockerignore keeps the build context to the files copied below.
#
# Two stages: the first builds the package's wheel, compiling its C kernels with Debian's
# gcc; the second installs the lock and that wheel and carries no compiler.
FROM python:3.11.7-slim-bookworm AS build

RUN apt-get update \
 && apt-get install -y --no-install-recommends gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /opt/geoidspline
COPY pyproject.toml README.md ./
COPY geoidspline ./geoidspline
COPY cli ./cli
COPY grids ./grids
# the README's `pip install .`, as a wheel (cli/ and grids/ install as geoidspline.cli and
# geoidspline.grids)
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM python:3.11.7-slim-bookworm

# egm96_15.gtx (and PROJ's other grids) in /usr/share/proj, where the catalogue looks
RUN apt-get update \
 && apt-get install -y --no-install-recommends proj-data \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 1000 --shell /usr/sbin/nologin geoid \
 && mkdir -p /data \
 && chown geoid:geoid /data

ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /opt/geoidspline
COPY requirements.lock ./
RUN pip install -r requirements.lock
# The wheel with the plot extra, so geoid-plot works in the image; --no-index: everything
# it needs must already be installed from the lock. Then the installed set must be the
# lock exactly, and consistent. Nothing is compiled at run time.
COPY --from=build /wheels /wheels
RUN pip install --no-index --find-links /wheels 'geoidspline[plot]' \
 && pip freeze --exclude geoidspline | diff -u requirements.lock - \
 && pip check \
 && rm -rf /wheels

USER geoid
WORKDIR /data
VOLUME ["/data"]
CMD ["geoid-info", "--help"]
