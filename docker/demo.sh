#!/usr/bin/env bash
# Runs a compose demo to its end, with compose v2 (`docker compose`) or v1 (`docker-compose`):
#
#   docker/demo.sh [docker-compose.yml | docker-compose.hosts.yml]
#
# Starts every service detached (in dependency order: credentials, world, then the agents or the
# routers and hosts), waits for the world's exit, prints the world's output (its table; its log lines
# on stderr), removes the containers, the network and the credentials volume, and exits with the
# world's status (docs/docker.md). The one-shot credentials service ends early by design, which is why
# this does not use `up --abort-on-container-exit`. Ctrl-C or SIGTERM removes the stack as well.
# The results are in ./results (or $DISKF_RESULTS), owned by you (DISKF_UID/DISKF_GID default to your
# ids). The image is built if it is missing; after a change run `docker compose build` first.
# COMPOSE_PROJECT_NAME names the stack (default: the folder's name), as compose itself does.
set -euo pipefail
cd "$(dirname "$0")/.."
file=${1:-docker-compose.yml}
[ -f "$file" ] || { echo "error: no compose file $file" >&2; exit 2; }
if docker compose version >/dev/null 2>&1; then
    compose=(docker compose -f "$file")
elif command -v docker-compose >/dev/null 2>&1; then
    compose=(docker-compose -f "$file")
else
    echo "error: neither 'docker compose' nor 'docker-compose' is installed" >&2
    exit 2
fi
export DISKF_UID=${DISKF_UID:-$(id -u)} DISKF_GID=${DISKF_GID:-$(id -g)}
mkdir -p "${DISKF_RESULTS:-results}"
DISKF_RESULTS=$(cd "${DISKF_RESULTS:-results}" && pwd)
export DISKF_RESULTS

down() { "${compose[@]}" down --volumes --timeout 10 >/dev/null 2>&1 || true; }
trap down EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
if ! "${compose[@]}" up --detach; then  # the world failed before the agents started: say why, with its status
    world=$("${compose[@]}" ps -q world)
    [ -n "$world" ] || exit 1
    docker logs "$world" >&2
    status=$(docker inspect -f '{{.State.ExitCode}}' "$world")
    exit "$(( status == 0 ? 1 : status ))"
fi
world=$("${compose[@]}" ps -q world)
status=$(docker wait "$world")
docker logs "$world"
echo "world exit status $status; results in $DISKF_RESULTS" >&2
exit "$status"
