#!/usr/bin/env bash
# The Prometheus Operator's CustomResourceDefinitions (ServiceMonitor, PodMonitor, PrometheusRule...), taken from its
# Go module through the Go module proxy into the kuberos cache (go/mod), for the test that applies the controller
# role's monitoring objects to a cluster that has those kinds. Prints the folder of the CRD files. Idempotent: a
# second run reads the module cache and downloads nothing.
set -euo pipefail
VERSION=${PROMETHEUS_OPERATOR_VERSION:-v0.85.0}
crds=$("$(dirname "$0")/go-module-path.sh" "github.com/prometheus-operator/prometheus-operator@$VERSION" \
  example/prometheus-operator-crd)
if [ ! -f "$crds/monitoring.coreos.com_servicemonitors.yaml" ]; then
  echo "operator-crds: $crds has no monitoring.coreos.com_servicemonitors.yaml" >&2
  exit 1
fi
echo "$crds"
