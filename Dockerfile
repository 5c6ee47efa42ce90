# One image for every process of a mesh run (see docker-compose.yml, docs/docker.md).
# The base image is pinned to one Python release; pin its digest too (FROM ...@sha256:...)
# where the registry is reachable to look it up.
FROM python:3.11.9-slim-bookworm
WORKDIR /app
# the dependencies from the lock first (a layer that changes only with it), then diskf-mesh itself:
# no plotting stack (matplotlib is the figures extra)
COPY requirements.lock /app/
RUN pip install --no-cache-dir -r requirements.lock
COPY . /app
# the processes run from /app (python -m sim.world): its bytecode compiled here, not by each process at start
RUN pip install --no-cache-dir --no-deps . \
 && python -m compileall -q /app \
 && useradd --uid 10001 --no-create-home --shell /usr/sbin/nologin diskf \
 && mkdir -p /credentials /results \
 && chmod 1777 /credentials /results
# every process runs this checkout's code (/app: python -m sim.world, diskf-mesh), from any working directory
ENV PYTHONPATH=/app
# not root: every service runs as this user, or as the DISKF_UID:DISKF_GID compose gives it;
# /credentials (a volume) takes any user's 0700 run directory, like /tmp
USER 10001
# zenoh peers listen here (TLS); the world's port is what agents connect to
EXPOSE 7447
CMD ["diskf-mesh", "--help"]
