# One image for every foldwise role (api, scheduler, render and train workers, migrate);
# compose.yaml picks the role with the command. Build: `docker compose build` (BuildKit, the
# default builder since Docker 23, for the RUN --mount below).

# --- the project itself, as a wheel: rebuilt on every code change, and cheap ---------------
FROM python:3.11-slim-bookworm AS wheel
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_ROOT_USER_ACTION=ignore
WORKDIR /src
# README.md is optional (the glob lets the build go on without it); pyproject names it.
COPY pyproject.toml README.md* ./
COPY foldwise/ foldwise/
COPY db/ db/
COPY workers/ workers/
COPY services/ services/
RUN pip wheel --no-deps --wheel-dir /wheels .

# --- the runtime --------------------------------------------------------------------------
FROM python:3.11-slim-bookworm

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_ROOT_USER_ACTION=ignore

# What bpy 5.0.1 links against outside its wheel (`ldd`/`readelf -d` of its shared objects): X11
# client libraries, libxkbcommon and the GL dispatch library. Checked on a bare Debian bookworm
# with only these installed: `import bpy` and a Cycles render through workers/render/blender.py
# work. No X server and no EGL: Cycles renders on the CPU (or CUDA/OptiX from the host driver)
# without a GL context. Left out on purpose: libxt6 and libopengl0 (only bpy's bundled MaterialX
# GLSL Python module wants them) and libegl1 (EEVEE's offscreen context; foldwise uses Cycles).
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
        libx11-6 libxext6 libxrender1 libxfixes3 libxi6 libxkbcommon0 libsm6 libice6 libgl1 \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 1000 --shell /usr/sbin/nologin foldwise \
 && mkdir -p /data \
 && chown foldwise:foldwise /data

WORKDIR /app

# Dependencies first, from the package metadata alone (empty packages stand in for the code),
# so that a code change reuses this layer instead of reinstalling torch and bpy. The same
# constraints file and extras as `make install`, less the dev tools.
COPY pyproject.toml constraints.txt ./
RUN mkdir -p foldwise db workers services \
 && touch foldwise/__init__.py db/__init__.py workers/__init__.py services/__init__.py README.md \
 && pip install -c constraints.txt '.[all]' \
 && pip uninstall -y foldwise \
 && rm -rf foldwise db workers services README.md build ./*.egg-info

# The code: only the wheel built above (bind-mounted, so it leaves no layer behind).
RUN --mount=type=bind,from=wheel,source=/wheels,target=/wheels \
    pip install --no-deps -c constraints.txt /wheels/foldwise-*.whl

# The render pipeline's numba kernels (paper model, rasteriser, occluder placement), compiled
# once into the image: a render worker process loads them in ~1 s instead of compiling for
# ~35 s on its first images. The runtime user must own the
# cache (numba passes over a cache directory it cannot write to, and compiles again).
ENV NUMBA_CACHE_DIR=/app/numba-cache
RUN python -c "from workers.render.pipeline import compile_kernels; compile_kernels()" \
 && chown -R foldwise:foldwise /app/numba-cache

# Experiment configs and Table 3 (read at run time from FOLDWISE_CONFIGS_DIR).
COPY configs/ configs/

# The artifact store is the shared volume compose mounts at /data. Torch's hub cache lives there
# too: ImageNet weights put once into /data/torch/hub/checkpoints serve every train worker
# (nothing is downloaded at run time).
ENV FOLDWISE_DATA_DIR=/data \
    FOLDWISE_CONFIGS_DIR=/app/configs \
    TORCH_HOME=/data/torch

USER foldwise
VOLUME ["/data"]

# Every role is a `foldwise` sub-command; compose.yaml names which one each service runs.
CMD ["foldwise", "--help"]
