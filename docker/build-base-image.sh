#!/usr/bin/env bash
# Builds a stand-in for the Dockerfile's base image (its FROM line) from Debian packages, for a machine
# where that image cannot be pulled (no image registry reachable) but Debian's packages can be installed.
#
#   docker/build-base-image.sh [--force]
#
# The stand-in is Debian (the suite named in the tag, e.g. bookworm) with its python3, pip and
# python-is-python3, imported into the local engine under the FROM tag, so that `docker compose build`
# runs the Dockerfile unchanged. It carries this host's configuration for reaching the package index:
#   - the CA certificates: the host's bundle (/etc/ssl/certs/ca-certificates.crt) and
#     /usr/local/share/ca-certificates/, so that a proxy that re-signs TLS is trusted in the build too;
#   - pip's configuration as `pip config list` shows it here (files and PIP_* variables) as the image's
#     /etc/pip.conf, with the files it names (a cert or constraints file) copied to the same paths;
#     local directories and file:// indexes are left out (a line on stderr says which);
#   - https_proxy/http_proxy, as pip's `proxy` when pip has none (apt uses them while building).
# Debian marks its Python as externally managed; the stand-in removes that marker, as the official
# image has none. Needs mmdebstrap (apt-get install mmdebstrap) and a running Docker engine.
# An image already present under the tag is kept (exit 0) unless --force is given.
# Environment: DEBIAN_MIRROR (default http://deb.debian.org/debian), PYTHON (whose pip configuration
# to carry; default python3).
set -euo pipefail
cd "$(dirname "$0")/.."

force=0
case "${1:-}" in
    --force) force=1 ;;
    "") ;;
    *) echo "error: usage: $0 [--force]" >&2; exit 2 ;;
esac
tag=$(awk '$1 == "FROM" {print $2; exit}' Dockerfile)
suite=${tag##*-}  # python:3.11.9-slim-bookworm -> bookworm
if [ -z "$tag" ] || ! [[ "$suite" =~ ^[a-z]+$ ]]; then
    echo "error: Dockerfile: FROM names no Debian suite at the end of its tag: '$tag'" >&2
    exit 2
fi
if [ "$force" = 0 ] && docker image inspect "$tag" >/dev/null 2>&1; then
    echo "$tag is already present"
    exit 0
fi
command -v mmdebstrap >/dev/null || { echo "error: mmdebstrap is not installed (apt-get install mmdebstrap)" >&2; exit 2; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# pip's configuration on this host -> $work/pip.conf and the list of files it names
"${PYTHON:-python3}" - "$work" <<'EOF'
import configparser, os, subprocess, sys
from urllib.parse import urlparse

work = sys.argv[1]
listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True).stdout
conf = configparser.ConfigParser(interpolation=None)
files, left_out = [], set()
for line in listed.splitlines():
    name, _, value = line.partition("=")
    section, _, key = name.rpartition(".")
    section = "global" if section == ":env:" else section
    kept = []
    for token in value.strip("'\"").split():
        path = urlparse(token).path if token.startswith("file:") else token
        if os.path.isfile(path) and os.path.isabs(path) and not token.startswith("file:"):
            files.append(path)  # a cert or constraints file: copied to the same path
        elif os.path.exists(path) or token.startswith("file:"):
            if (key, token) not in left_out:
                print(f"note: pip's {key} {token} is a local directory or index: not carried into the image",
                      file=sys.stderr)
            left_out.add((key, token))
            continue
        kept.append(token)
    if kept:
        conf.setdefault(section, {})[key] = " ".join(kept)
proxy = os.environ.get("https_proxy") or os.environ.get("HTTPS_PROXY") or os.environ.get("http_proxy")
if proxy and not any("proxy" in conf[s] for s in conf.sections()):
    conf.setdefault("global", {})["proxy"] = proxy
with open(os.path.join(work, "pip.conf"), "w") as f:
    conf.write(f)
with open(os.path.join(work, "files"), "w") as f:
    f.write("".join(sorted({p + "\n" for p in files})))
EOF

hooks=(--customize-hook='rm -f "$1"/usr/lib/python3*/EXTERNALLY-MANAGED'
       --customize-hook="copy-in $work/pip.conf /etc")
while read -r f; do
    hooks+=(--customize-hook="mkdir -p \"\$1$(dirname "$f")\"" --customize-hook="copy-in $f $(dirname "$f")")
done < "$work/files"
for f in /etc/ssl/certs/ca-certificates.crt /usr/local/share/ca-certificates/*; do
    [ -f "$f" ] && hooks+=(--customize-hook="mkdir -p \"\$1$(dirname "$f")\"" --customize-hook="copy-in $f $(dirname "$f")")
done
echo "building $tag from Debian $suite (python3, pip) with this host's CA certificates and pip configuration:"
sed 's/^/    /' "$work/pip.conf"
mmdebstrap --quiet --variant=minbase --include=ca-certificates,python3,python3-pip,python-is-python3,passwd \
    --aptopt='Acquire::Retries "3"' "${hooks[@]}" \
    --customize-hook='rm -rf "$1"/var/lib/apt/lists/* "$1"/var/cache/apt/*.bin' \
    "$suite" "$work/rootfs.tar" "${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change "LABEL org.opencontainers.image.description=\"stand-in for $tag built from Debian $suite packages by docker/build-base-image.sh\"" \
    --change 'CMD ["python3"]' \
    "$work/rootfs.tar" "$tag" >/dev/null
echo "$tag: $(docker image inspect -f '{{.Size}}' "$tag" | awk '{printf "%.0f MB", $1 / 1e6}')"
