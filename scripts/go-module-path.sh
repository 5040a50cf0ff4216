#!/usr/bin/env bash
# Usage: go-module-path.sh MODULE@VERSION PATH
# Print where PATH (a file or folder inside the module) is once MODULE@VERSION is in the kuberos cache's Go module
# cache (go/mod), downloading it through the Go module proxy the first time: files a test needs from a project's
# published sources (the Prometheus Operator's CRDs, Calico's manifests). Fails naming the module and the path.
set -euo pipefail
[ $# -eq 2 ] || { echo "usage: $(basename "$0") MODULE@VERSION PATH" >&2; exit 2; }
CACHE_DIR=${KUBEROS_CACHE_DIR:-${HOME:?HOME is not set}/.cache/kuberos}
GO=${GO:-go}
command -v "$GO" >/dev/null 2>&1 || GO=/usr/local/go/bin/go
export GOMODCACHE="$CACHE_DIR/go/mod" GOFLAGS=-modcacherw GOTOOLCHAIN="${GOTOOLCHAIN:-local}" GOWORK=off
mkdir -p "$CACHE_DIR/work"
cd "$CACHE_DIR/work"  # outside any module
dir=$("$GO" mod download -json "$1" | sed -n 's/^[[:space:]]*"Dir": "\(.*\)",\{0,1\}$/\1/p')
if [ -z "$dir" ] || [ ! -e "$dir/$2" ]; then
  echo "$(basename "$0"): $1 has no $2 (go mod download: ${dir:-failed})" >&2
  exit 1
fi
echo "$dir/$2"
