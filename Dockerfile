# One image for `drop api` and `drop worker`; the command picks the role.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home --uid 1000 drop
WORKDIR /srv/drop

COPY pyproject.toml constraints.txt README.md ./
COPY drop_engine ./drop_engine
COPY kernel ./kernel
COPY app ./app
COPY worker ./worker
COPY drop_client ./drop_client
COPY drop_cli ./drop_cli
COPY migrations ./migrations
COPY alembic.ini ./
# torch==2.13.0 from constraints.txt; point PIP_EXTRA_INDEX_URL at a CPU-only wheel index for a smaller image.
ARG PIP_EXTRA_INDEX_URL=
RUN pip install -c constraints.txt -e .

USER drop
ENV DROP_DATA_DIR=/data
EXPOSE 8000
CMD ["drop", "api", "--host", "0.0.0.0", "--port", "8000"]
