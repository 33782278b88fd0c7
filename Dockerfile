# osdar-ar: one image for the API and the workers (docker-compose.yml picks the command).
FROM python:3.11-slim-bookworm

# Mesa EGL + llvmpipe (moderngl renders headless on the CPU; a GPU driver replaces it),
# libusb-1.0 and libgomp (open3d's wheel links them), curl for the health checks.
RUN apt-get update -q \
 && apt-get install -y -q --no-install-recommends \
      libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libusb-1.0-0 libgomp1 curl \
 && rm -rf /var/lib/apt/lists/*

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    OSDAR_AR_DATA_DIR=/data

WORKDIR /app
# Dependencies first (cached layer), then the code.
COPY pyproject.toml README.md ./
RUN mkdir -p service worker renderer geometry osdar_platform \
 && touch service/__init__.py worker/__init__.py renderer/__init__.py \
      geometry/__init__.py osdar_platform/__init__.py \
 && pip install . \
 && pip uninstall -y osdar-ar
COPY alembic.ini ./
COPY migrations ./migrations
COPY service ./service
COPY worker ./worker
COPY renderer ./renderer
COPY geometry ./geometry
COPY osdar_platform ./osdar_platform
# Editable-style layout: migrations/ is found next to the package (osdar_platform/migrate.py).
RUN pip install --no-deps -e . \
 && useradd --create-home --uid 10001 osdar \
 && mkdir -p /data && chown osdar /data
USER osdar
VOLUME ["/data"]
EXPOSE 8000
CMD ["osdar-ar", "serve", "--host", "0.0.0.0", "--port", "8000"]
