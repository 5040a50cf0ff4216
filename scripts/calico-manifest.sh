#!/usr/bin/env bash
# Calico's published manifest for a VXLAN cluster (manifests/calico-vxlan.yaml of Calico's repository), taken from
# Calico's Go module through the Go module proxy into the kuberos cache (go/mod), for the tests that check the calico
# role against the real API server. The module proxy serves Calico's repository at one commit of the release-v3.28
# branch, whose manifests are those of release v3.28.5. Prints the manifest's path. Idempotent: a second run reads the
# module cache and downloads nothing.
set -euo pipefail
VERSION=${CALICO_MODULE_VERSION:-v1.11.0-cni-plugin.0.20250813170300-a0db560f0520}
CACHE_DIR=${KUBEROS_CACHE_DIR:-${HOME:?HOME is not set}/.cache/kuberos}
GO=${GO:-go}
command -v "$GO" >/dev/null 2>&1 || GO=/usr/local/go/bin/go
export GOMODCACHE="$CACHE_DIR/go/mod" GOFLAGS=-modcacherw GOTOOLCHAIN="${GOTOOLCHAIN:-local}" GOWORK=off
mkdir -p "$CACHE_DIR/work"
cd "$CACHE_DIR/work"  # outside any module
module="github.com/projectcalico/calico@$VERSION"
dir=$("$GO" mod download -json "$module" | sed -n 's/^[[:space:]]*"Dir": "\(.*\)",\{0,1\}$/\1/p')
manifest="$dir/manifests/calico-vxlan.yaml"
if [ -z "$dir" ] || [ ! -f "$manifest" ]; then
  echo "calico-manifest: $module has no manifests/calico-vxlan.yaml (go mod download: ${dir:-failed})" >&2
  exit 1
fi
echo "$manifest"
