#!/usr/bin/env bash
# The Prometheus Operator's CustomResourceDefinitions (ServiceMonitor, PodMonitor, PrometheusRule...), taken from its
# Go module through the Go module proxy into the kuberos cache (go/mod), for the test that applies the controller
# role's monitoring objects to a cluster that has those kinds. Prints the folder of the CRD files. Idempotent: a
# second run reads the module cache and downloads nothing.
set -euo pipefail
VERSION=${PROMETHEUS_OPERATOR_VERSION:-v0.85.0}
CACHE_DIR=${KUBEROS_CACHE_DIR:-${HOME:?HOME is not set}/.cache/kuberos}
GO=${GO:-go}
command -v "$GO" >/dev/null 2>&1 || GO=/usr/local/go/bin/go
export GOMODCACHE="$CACHE_DIR/go/mod" GOFLAGS=-modcacherw GOTOOLCHAIN="${GOTOOLCHAIN:-local}" GOWORK=off
mkdir -p "$CACHE_DIR/work"
cd "$CACHE_DIR/work"  # outside any module
module="github.com/prometheus-operator/prometheus-operator@$VERSION"
dir=$("$GO" mod download -json "$module" | sed -n 's/^[[:space:]]*"Dir": "\(.*\)",\{0,1\}$/\1/p')
crds="$dir/example/prometheus-operator-crd"
if [ -z "$dir" ] || [ ! -f "$crds/monitoring.coreos.com_servicemonitors.yaml" ]; then
  echo "operator-crds: $module has no CRDs at example/prometheus-operator-crd (go mod download: ${dir:-failed})" >&2
  exit 1
fi
echo "$crds"
