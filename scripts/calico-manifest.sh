#!/usr/bin/env bash
# Calico's published manifest for a VXLAN cluster (manifests/calico-vxlan.yaml of Calico's repository), from Calico's
# Go module through the Go module proxy, for the tests that check the calico role against the real API server. The
# module proxy serves Calico's repository at one commit of the release-v3.28 branch, whose manifests are those of
# release v3.28.5. Prints the manifest's path; a second run downloads nothing.
set -euo pipefail
VERSION=${CALICO_MODULE_VERSION:-v1.11.0-cni-plugin.0.20250813170300-a0db560f0520}
exec "$(dirname "$0")/go-module-path.sh" "github.com/projectcalico/calico@$VERSION" manifests/calico-vxlan.yaml
