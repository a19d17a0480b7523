#!/usr/bin/env bash
# Build a local Python 3.11 base image from Debian's own packages, for machines without Docker Hub.
#
#   docker/build_base_image.sh [--force] [TAG]        # default TAG: hoi-refine-base:bookworm
#   docker build --network host --build-arg BASE_IMAGE=hoi-refine-base:bookworm -t hoi-refine:latest .
#
# debootstrap installs a minimal Debian 12 (bookworm: python3 is 3.11, as in python:3.11-slim) with python3,
# python3-venv, python3-pip and ca-certificates; the result is imported with `docker import`. The image gets
#   * this machine's CA bundle (/etc/ssl/certs/ca-certificates.crt), so HTTPS from inside a build (pip) trusts
#     what the host trusts (a TLS-inspecting proxy's CA included);
#   * a virtual environment at /opt/venv, first on PATH: `python` and `pip` then mean what they mean in
#     python:3.11-slim, and pip may install without Debian's "externally managed" guard (PEP 668);
#   * /etc/pip.conf with the CA bundle and this machine's index settings that can work inside a container (the
#     index URL and timeout; file:// indexes and find-links of the host are not carried: they are not there).
# Idempotent: an existing TAG is kept unless --force. Needs root, debootstrap and a running dockerd.
set -euo pipefail

FORCE=0
if [[ "${1:-}" == "--force" ]]; then FORCE=1; shift; fi
TAG="${1:-hoi-refine-base:bookworm}"
SUITE=bookworm
# The host's Debian mirror (apt sources), so the base image comes from where this machine's packages come from.
MIRROR="${DEBIAN_MIRROR:-$(grep -hoE '^URIs: *http[^ ]*/debian$' /etc/apt/sources.list.d/*.sources 2>/dev/null \
  | head -n1 | sed -E 's/^URIs: *//')}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"
HOST_CA=/etc/ssl/certs/ca-certificates.crt

if [[ $FORCE -eq 0 ]] && docker image inspect "$TAG" >/dev/null 2>&1; then
  echo "base image $TAG exists (use --force to rebuild)"
  exit 0
fi
for tool in debootstrap docker; do
  command -v "$tool" >/dev/null || { echo "error: $tool is not installed (apt-get install debootstrap docker.io)" >&2; exit 2; }
done
[[ $(id -u) -eq 0 ]] || { echo "error: debootstrap needs root" >&2; exit 2; }

ROOTFS="$(mktemp -d /var/tmp/hoi-refine-rootfs.XXXXXX)"
trap 'rm -rf --one-file-system "$ROOTFS"' EXIT

echo "debootstrap $SUITE from $MIRROR into $ROOTFS"
debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
  "$SUITE" "$ROOTFS" "$MIRROR"

if [[ -f "$HOST_CA" ]]; then
  # As a local CA file: update-ca-certificates appends it to the bundle, now and on any later run in the image.
  install -m 0644 "$HOST_CA" "$ROOTFS/usr/local/share/ca-certificates/host-ca-bundle.crt"
  # (its "rehash: skipping ... bundle" warnings are about the bundles themselves and harmless)
  chroot "$ROOTFS" update-ca-certificates >/dev/null 2>&1
fi

chroot "$ROOTFS" python3 -m venv /opt/venv

{
  echo "[global]"
  echo "cert = /etc/ssl/certs/ca-certificates.crt"
  # The host's remote index settings only (a file:// index or find-links folder does not exist in a container).
  for key in global.index-url global.timeout; do
    value="$(pip config get "$key" 2>/dev/null || true)"
    [[ -n "$value" && "$value" != file:* ]] && echo "${key#global.} = $value"
  done
  [[ -n "${PIP_INDEX_URL:-}" && "${PIP_INDEX_URL}" != file:* ]] && echo "index-url = $PIP_INDEX_URL"
  [[ -n "${PIP_DEFAULT_TIMEOUT:-}" ]] && echo "timeout = $PIP_DEFAULT_TIMEOUT"
  true
} >"$ROOTFS/etc/pip.conf"

# Leaner: no apt lists or caches, no docs (the image only ever runs Python).
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/var/cache/apt/archives/*.deb \
  "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/locale/*

tar -C "$ROOTFS" --numeric-owner -c . | docker import \
  --change 'ENV PATH=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' \
  --change 'ENV SSL_CERT_FILE=/etc/ssl/certs/ca-certificates.crt' \
  --change 'CMD ["python3"]' \
  - "$TAG"
docker run --rm --network none "$TAG" python -c 'import sys, ssl; print("base image python", sys.version.split()[0], ssl.OPENSSL_VERSION)'
echo "built $TAG"
