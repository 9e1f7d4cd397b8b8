# One image for every curlnav role: `docker run curlnav <role>` runs `curlnav serve <role>`.
#
# BASE_IMAGE: any Debian-like image with Python 3.11 and venv (default: the official slim image).
# Without registry access, build FROM a local base (scripts/make-base-image.sh) and install from a
# wheelhouse made on the host (scripts/make-wheelhouse.sh); wheelhouse/ may stay empty otherwise.
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV VIRTUAL_ENV=/opt/curlnav PATH=/opt/curlnav/bin:$PATH PYTHONUNBUFFERED=1 MPLBACKEND=Agg

# Dependency layer: changes only when docker/requirements.txt or the wheelhouse changes.
COPY docker/requirements.txt /tmp/requirements.txt
COPY wheelhouse/ /tmp/wheelhouse/
RUN PY=$(command -v python3.11 || command -v python3) && "$PY" -m venv "$VIRTUAL_ENV" \
 && if ls /tmp/wheelhouse/*.whl >/dev/null 2>&1; then \
      pip install --no-cache-dir --no-index --find-links /tmp/wheelhouse -r /tmp/requirements.txt; \
    else \
      pip install --no-cache-dir --extra-index-url https://download.pytorch.org/whl/cpu -r /tmp/requirements.txt; \
    fi \
 && rm -rf /tmp/wheelhouse /root/.cache

# Code layer.
COPY pyproject.toml README.md /src/
COPY curlnav /src/curlnav
COPY actor /src/actor
COPY learner /src/learner
COPY replay /src/replay
COPY scheduler /src/scheduler
COPY proto /src/proto
RUN pip install --no-cache-dir --no-deps --no-build-isolation /src \
 && python -c "from curlnav.sim.geometry import warm_up; warm_up()"  # numba kernels compiled into the image

RUN useradd --create-home --uid 10001 curlnav && mkdir -p /data /curricula && chown curlnav /data
USER curlnav
WORKDIR /data
ENV CURLNAV_DATA_DIR=/data
ENTRYPOINT ["curlnav", "serve"]
CMD ["--help"]
