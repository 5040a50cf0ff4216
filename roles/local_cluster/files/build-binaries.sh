#!/usr/bin/env bash
# Build a local Kubernetes control plane (kube-apiserver, kube-controller-manager,
# kube-scheduler, kubectl), etcd with its tools (etcdctl, etcdutl) and kwok, and for real
# nodes kubelet, kube-proxy and CoreDNS, from their Go modules, with the ordinary
# `go` client and the Go module proxy only (no release downloads, no images).
#
# Binaries land in a cache outside the repository, keyed by version:
#   ${KUBEROS_CACHE_DIR:-$HOME/.cache/kuberos}/bin/<program>-<version>
# The Go module cache and build cache live under the same directory
# (go/mod, go/build), so CI can cache one directory. Run `--help` for options.
# Every long step prints a line at least every 30 s (KUBEROS_PROGRESS_INTERVAL) and its time when it ends.
set -euo pipefail

SCRIPT_NAME=$(basename "$0")
# shellcheck source=SCRIPTDIR/progress.sh
source "$(dirname "${BASH_SOURCE[0]}")/progress.sh"
# shellcheck source=SCRIPTDIR/go-build.sh
source "$(dirname "${BASH_SOURCE[0]}")/go-build.sh"

usage() {
  cat <<EOF
Usage: $SCRIPT_NAME [--print-paths] [--help]

Build kube-apiserver, kube-controller-manager, kube-scheduler, kubectl, kubeadm,
etcd, etcdctl, etcdutl and kwok (and kubelet, kube-proxy and CoreDNS for real nodes) from the Go module proxy into a version-keyed cache. Programs already in the
cache (and answering --version with the expected version) are not rebuilt.

Options:
  --print-paths   Do not build; print name=path for each cached binary and exit
                  (exit 1, with a message on stderr, if any is missing).
                  Same as KUBEROS_PRINT_PATHS=1.
  -h, --help      Show this help.

Environment (defaults in brackets):
  KUBERNETES_VERSION   k8s.io/kubernetes release              [v1.34.4]
  ETCD_VERSION         go.etcd.io/etcd/server/v3 release      [v3.5.35]
                       (etcdctl and etcdutl: go.etcd.io/etcd/{etcdctl,etcdutl}/v3 at the same version)
  KWOK_VERSION         sigs.k8s.io/kwok release               [v0.8.0]
  COREDNS_VERSION      github.com/coredns/coredns release     [v1.14.7]
  SKIP_KUBECTL=1       do not build (or require) kubectl      [0]
  SKIP_KUBEADM=1       do not build (or require) kubeadm      [0]
                       (kubeadm: the cluster setup roles' config checks and tests)
  SKIP_NODES=1         do not build (or require) kubelet, kube-proxy and CoreDNS [1]
                       (the real-node tier of the local cluster, docs/real-nodes.md)
  KUBEROS_CACHE_DIR    cache root                  [\$HOME/.cache/kuberos]
  KUBEROS_BUILD_JOBS   go build -p value                      [2]
  KUBEROS_PROGRESS_INTERVAL  seconds between progress lines of a long step [30]
  GO                   go command                 [go on PATH, else /usr/local/go/bin/go]
  GOPROXY, GOSUMDB, GOTOOLCHAIN are honoured (GOTOOLCHAIN defaults to local).

Layout under the cache root:
  bin/<program>-<version>   the binaries
  go/mod, go/build          GOMODCACHE and GOCACHE
  work/                     generated wrapper modules (go.mod/go.sum)
EOF
}

KUBERNETES_VERSION=${KUBERNETES_VERSION:-v1.34.4}
ETCD_VERSION=${ETCD_VERSION:-v3.5.35}
KWOK_VERSION=${KWOK_VERSION:-v0.8.0}
COREDNS_VERSION=${COREDNS_VERSION:-v1.14.7}
SKIP_NODES=${SKIP_NODES:-1}
SKIP_KUBECTL=${SKIP_KUBECTL:-0}
SKIP_KUBEADM=${SKIP_KUBEADM:-0}
BUILD_JOBS=${KUBEROS_BUILD_JOBS:-2}
PRINT_PATHS=${KUBEROS_PRINT_PATHS:-0}

go_build_args "$@"

# --- versions and programs ----------------------------------------------------

[[ $KUBERNETES_VERSION =~ ^v1\.([0-9]+)\.([0-9]+)(-[0-9A-Za-z.]+)?$ ]] \
  || die "KUBERNETES_VERSION must look like v1.34.4, got '$KUBERNETES_VERSION'"
KUBE_MINOR=${BASH_REMATCH[1]}
STAGING_VERSION="v0.${KUBERNETES_VERSION#v1.}"   # v1.34.4 -> v0.34.4
[[ $ETCD_VERSION =~ ^v3\.[0-9]+\.[0-9]+(-[0-9A-Za-z.]+)?$ ]] \
  || die "ETCD_VERSION must look like v3.5.21, got '$ETCD_VERSION'"
[[ $KWOK_VERSION =~ ^v[0-9]+\.[0-9]+\.[0-9]+(-[0-9A-Za-z.]+)?$ ]] \
  || die "KWOK_VERSION must look like v0.7.0, got '$KWOK_VERSION'"
[[ $COREDNS_VERSION =~ ^v1\.[0-9]+\.[0-9]+$ ]] \
  || die "COREDNS_VERSION must look like v1.14.7, got '$COREDNS_VERSION'"

K8S_PROGRAMS=(kube-apiserver kube-controller-manager kube-scheduler)
[[ $SKIP_KUBECTL == 1 ]] || K8S_PROGRAMS+=(kubectl)
[[ $SKIP_KUBEADM == 1 ]] || K8S_PROGRAMS+=(kubeadm)
[[ $SKIP_NODES == 1 ]] || K8S_PROGRAMS+=(kubelet kube-proxy)
# etcd's own tools go wherever etcd goes: upstream's etcd image carries them, and so does the lab's (the site's
# backup, restore and health checks run them inside the etcd pod or from its image).
ETCD_PROGRAMS=(etcd etcdctl etcdutl)
PROGRAMS=("${K8S_PROGRAMS[@]}" "${ETCD_PROGRAMS[@]}" kwok)
[[ $SKIP_NODES == 1 ]] || PROGRAMS+=(coredns)

version_of() {
  case $1 in
    etcd | etcdctl | etcdutl) echo "$ETCD_VERSION" ;;
    kwok) echo "$KWOK_VERSION" ;;
    coredns) echo "$COREDNS_VERSION" ;;
    *) echo "$KUBERNETES_VERSION" ;;
  esac
}
path_of() { echo "$BIN_DIR/$1-$(version_of "$1")"; }

# Succeeds if binary $2 runs and reports the version expected for program $1.
binary_ok() {
  local name=$1 file=$2 out want
  [[ -f $file && -x $file ]] || return 1
  case $name in
    kubectl) out=$(timeout 60 "$file" version --client 2>&1) || return 1
             want="Client Version: $KUBERNETES_VERSION" ;;
    kubeadm) out=$(timeout 60 "$file" version -o short 2>&1) || return 1
             want="$KUBERNETES_VERSION" ;;
    etcd) out=$(timeout 60 "$file" --version 2>&1) || return 1
          want="etcd Version: ${ETCD_VERSION#v}" ;;
    etcdctl | etcdutl) out=$(timeout 60 "$file" version 2>&1) || return 1
                       want="$name version: ${ETCD_VERSION#v}" ;;
    kwok) out=$(timeout 60 "$file" --version 2>&1) || return 1
          want="${KWOK_VERSION}" ;;
    coredns) out=$(timeout 60 "$file" -version 2>&1) || return 1
             # a build with another plugin set is stale too
             [[ $(timeout 60 "$file" -plugins 2>&1) == *loadbalance* ]] || return 1
             want="CoreDNS-${COREDNS_VERSION#v}" ;;
    *) out=$(timeout 60 "$file" --version 2>&1) || return 1
       want="Kubernetes $KUBERNETES_VERSION" ;;
  esac
  [[ $out == *"$want"* ]]
}

go_build_setup

log "cache: $CACHE_DIR ($("$GO" version | cut -d' ' -f3-), GOTOOLCHAIN=$GOTOOLCHAIN, -p $BUILD_JOBS)"
log "versions: kubernetes $KUBERNETES_VERSION (staging $STAGING_VERSION), etcd $ETCD_VERSION, kwok $KWOK_VERSION"

collect_todo

# How long a step takes with cold caches on 2 free cores, as measured (docs/local-cluster.md); shown with its
# progress lines. Other work on the machine makes it much longer.
about() {
  local when="on 2 free cores with cold caches"
  case $1 in
    kubernetes) if [[ $2 == "kube-apiserver kube-controller-manager kube-scheduler" ]]; then echo "about 6 min $when"; fi ;;
    etcd) echo "about 40 s $when" ;;
    etcdctl) echo "about 40 s $when, seconds after etcd (they share its packages)" ;;
    etcdutl) echo "seconds after etcd or etcdctl (it shares their packages)" ;;
    kwok) echo "about 1.5 min $when" ;;
    coredns) echo "about 2 min $when" ;;
  esac
}

wanted() { local p; for p in "${TODO[@]}"; do [[ $p == "$1" ]] && return 0; done; return 1; }

# Move freshly built $2 into place as program $1 after checking its version.
install_binary() {
  local name=$1 built=$2 dest
  dest=$(path_of "$name")
  STEP="checking $name"
  local ask=--version
  [[ $name != etcdctl && $name != etcdutl ]] || ask=version
  binary_ok "$name" "$built" || die "$name built at $built but does not report version $(version_of "$name"): $("$built" "$ask" 2>&1 | head -3)"
  mv -f "$built" "$dest"
}

# --- Kubernetes ----------------------------------------------------------------

build_kubernetes() {
  local todo=() p
  for p in "${K8S_PROGRAMS[@]}"; do wanted "$p" && todo+=("$p"); done
  ((${#todo[@]})) || return 0

  local t0=$SECONDS wrap="$WORK_DIR/kubernetes-$KUBERNETES_VERSION" upstream_mod go_line
  STEP="resolving k8s.io/kubernetes@$KUBERNETES_VERSION"
  log "$STEP"
  upstream_mod=$("$GO" list -m -f '{{.GoMod}}' "k8s.io/kubernetes@$KUBERNETES_VERSION") \
    || die "cannot resolve k8s.io/kubernetes@$KUBERNETES_VERSION from ${GOPROXY:-the Go module proxy}"
  go_line=$("$GO" list -m -f '{{.GoVersion}}' "k8s.io/kubernetes@$KUBERNETES_VERSION")

  # Staging modules: upstream replaces them with ./staging/src/...; we pin the
  # published k8s.io/<name> v0.<minor>.<patch> instead.
  local staging=()
  mapfile -t staging < <(awk '/=>[[:space:]]*\.\/staging\// {
      for (i = 1; i <= NF; i++) if ($i ~ /^k8s\.io\//) { print $i; break } }' "$upstream_mod")
  ((${#staging[@]})) || die "no staging replace directives found in $upstream_mod"
  local other
  other=$(grep -E '=>' "$upstream_mod" | grep -vE '=>[[:space:]]*\./staging/' || true)
  [[ -z $other ]] || log "note: upstream go.mod has other replace directives, not applied: $other"
  log "k8s.io/kubernetes $KUBERNETES_VERSION: go $go_line, ${#staging[@]} staging modules pinned at $STAGING_VERSION"

  mkdir -p "$wrap"
  {
    echo "module kuberos.local/build/kubernetes"
    echo
    echo "go $go_line"
    # keep upstream's godebug defaults (single-line and block form)
    awk '/^godebug[[:space:]]*\(/ {b=1} b || /^godebug[[:space:]]/ {print} b && /^\)/ {b=0}' "$upstream_mod"
    echo
    echo "require k8s.io/kubernetes $KUBERNETES_VERSION"
    echo
    echo "replace ("
    for p in "${staging[@]}"; do printf '\t%s => %s %s\n' "$p" "$p" "$STAGING_VERSION"; done
    echo ")"
  } >"$wrap/go.mod.new"
  mv -f "$wrap/go.mod.new" "$wrap/go.mod"

  local pkgs=() tags="selinux,notest,grpcnotrace"
  for p in "${todo[@]}"; do pkgs+=("k8s.io/kubernetes/cmd/$p"); done

  STEP="downloading modules for ${todo[*]} $KUBERNETES_VERSION"
  log "$STEP..."
  with_progress "$STEP" -- in_dir "$wrap" run_logged "$wrap.download.log" "$GO" list -mod=mod -deps -tags "$tags" "${pkgs[@]}" \
    || die "module download/resolution failed for k8s.io/kubernetes $KUBERNETES_VERSION (log: $wrap.download.log)"
  log "modules ready ($(downloads_in "$wrap.download.log"))"
  record_time "kubernetes modules (resolve+download)" $((SECONDS - t0))

  local ldflags="-s -w" k
  local build_date
  # buildDate: the release's publication time from the proxy (reproducible builds)
  build_date=$("$GO" list -m -f '{{with .Time}}{{.UTC.Format "2006-01-02T15:04:05Z"}}{{end}}' \
    "k8s.io/kubernetes@$KUBERNETES_VERSION" 2>/dev/null || true)
  [[ -n $build_date ]] || build_date=$(date -u +%Y-%m-%dT%H:%M:%SZ)
  for k in k8s.io/component-base/version k8s.io/client-go/pkg/version; do
    ldflags+=" -X $k.gitVersion=$KUBERNETES_VERSION -X $k.gitMajor=1 -X $k.gitMinor=$KUBE_MINOR"
    ldflags+=" -X $k.gitTreeState=clean -X $k.buildDate=$build_date"
  done

  local t1=$SECONDS out
  out=$(mktemp -d "$BIN_DIR/.build-k8s.XXXXXX"); TMP_DIRS+=("$out")
  local first last
  first=$(index_of "${todo[0]}"); last=$(index_of "${todo[-1]}")
  STEP="building ${todo[*]} $KUBERNETES_VERSION"
  log "building ${todo[*]} $KUBERNETES_VERSION ($first-$last/$TOTAL, one go build)..."
  BUILD_LOG="$wrap.build.log" PACKAGES_TOTAL=$(packages_in "$wrap.download.log")
  with_progress --about "$(about kubernetes "${todo[*]}")" --status packages_compiled "$STEP" -- \
      in_dir "$wrap" run_logged "$BUILD_LOG" "$GO" build -v -mod=mod -p "$BUILD_JOBS" -trimpath -tags "$tags" \
      -ldflags "$ldflags" -o "$out/" "${pkgs[@]}" \
    || die "go build failed for ${todo[*]} $KUBERNETES_VERSION (log: $BUILD_LOG)"
  for p in "${todo[@]}"; do install_binary "$p" "$out/$p"; done
  record_time "kubernetes build (${todo[*]})" $((SECONDS - t1))
}

# --- etcd ----------------------------------------------------------------------

# The Go module whose main package is program $1.
etcd_module_of() {
  case $1 in
    etcd) echo go.etcd.io/etcd/server/v3 ;;
    etcdctl) echo go.etcd.io/etcd/etcdctl/v3 ;;
    etcdutl) echo go.etcd.io/etcd/etcdutl/v3 ;;
  esac
}

# etcd, etcdctl and etcdutl at ETCD_VERSION, each from its own module in its own wrapper module (each program built
# with the dependency versions its own module requires, as upstream builds it).
build_etcd() {
  local p
  for p in "${ETCD_PROGRAMS[@]}"; do
    wanted "$p" && build_etcd_program "$p"
  done
  return 0
}

build_etcd_program() {
  local name=$1 mod go_line
  mod=$(etcd_module_of "$name")
  local t0=$SECONDS wrap="$WORK_DIR/$name-$ETCD_VERSION"
  STEP="resolving $mod@$ETCD_VERSION"
  log "$STEP"
  go_line=$("$GO" list -m -f '{{.GoVersion}}' "$mod@$ETCD_VERSION") \
    || die "cannot resolve $mod@$ETCD_VERSION from ${GOPROXY:-the Go module proxy}"
  # etcd's modules replace their sibling modules with ../api etc.; as a dependency of a wrapper module those
  # replaces are ignored and the published go.etcd.io/etcd/{api,client,pkg,raft,server} versions it requires are used.
  mkdir -p "$wrap"
  printf 'module kuberos.local/build/%s\n\ngo %s\n\nrequire %s %s\n' \
    "$name" "$go_line" "$mod" "$ETCD_VERSION" >"$wrap/go.mod.new"
  mv -f "$wrap/go.mod.new" "$wrap/go.mod"
  STEP="downloading modules for $name $ETCD_VERSION"
  log "$STEP..."
  with_progress "$STEP" -- in_dir "$wrap" run_logged "$wrap.download.log" "$GO" list -mod=mod -deps "$mod" \
    || die "module download/resolution failed for $name $ETCD_VERSION (log: $wrap.download.log)"
  log "modules ready ($(downloads_in "$wrap.download.log"))"
  record_time "$name modules (resolve+download)" $((SECONDS - t0))

  local t1=$SECONDS out
  out=$(mktemp -d "$BIN_DIR/.build-$name.XXXXXX"); TMP_DIRS+=("$out")
  STEP="building $name $ETCD_VERSION"
  log "building $name $ETCD_VERSION ($(index_of "$name")/$TOTAL)..."
  BUILD_LOG="$wrap.build.log" PACKAGES_TOTAL=$(packages_in "$wrap.download.log")
  with_progress --about "$(about "$name")" --status packages_compiled "$STEP" -- \
      in_dir "$wrap" run_logged "$BUILD_LOG" "$GO" build -v -mod=mod -p "$BUILD_JOBS" -trimpath -ldflags "-s -w" \
      -o "$out/$name" "$mod" \
    || die "go build failed for $name $ETCD_VERSION (log: $BUILD_LOG)"
  install_binary "$name" "$out/$name"
  record_time "$name build" $((SECONDS - t1))
}

# --- kwok ----------------------------------------------------------------------

build_kwok() {
  wanted kwok || return 0
  local t0=$SECONDS out
  out=$(mktemp -d "$BIN_DIR/.build-kwok.XXXXXX"); TMP_DIRS+=("$out")
  STEP="building kwok $KWOK_VERSION"
  log "building kwok $KWOK_VERSION ($(index_of kwok)/$TOTAL, go install, download included)..."
  # go install pkg@version uses kwok's own go.mod (it has no replace directives).
  BUILD_LOG="$WORK_DIR/kwok-$KWOK_VERSION.log" PACKAGES_TOTAL=""
  with_progress --about "$(about kwok)" --status packages_compiled "$STEP" -- \
      run_logged "$BUILD_LOG" env GOBIN="$out" "$GO" install -v -p "$BUILD_JOBS" -trimpath -ldflags "-s -w" \
      "sigs.k8s.io/kwok/cmd/kwok@$KWOK_VERSION" \
    || die "go install failed for sigs.k8s.io/kwok/cmd/kwok@$KWOK_VERSION (log: $BUILD_LOG)"
  install_binary kwok "$out/kwok"
  record_time "kwok (download+build)" $((SECONDS - t0))
  log "kwok: $(downloads_in "$BUILD_LOG")"
}

# --- CoreDNS -------------------------------------------------------------------

# The cluster DNS of the real-node tier. A wrapper main with the plugins a cluster's Corefile uses
# (bind, errors, log, health, ready, hosts, kubernetes, cache): the full plugin set would pull in every cloud
# provider's SDK for nothing.
build_coredns() {
  wanted coredns || return 0
  local t0=$SECONDS wrap="$WORK_DIR/coredns-$COREDNS_VERSION" mod=github.com/coredns/coredns go_line
  STEP="resolving $mod@$COREDNS_VERSION"
  log "$STEP"
  go_line=$("$GO" list -m -f '{{.GoVersion}}' "$mod@$COREDNS_VERSION") \
    || die "cannot resolve $mod@$COREDNS_VERSION from ${GOPROXY:-the Go module proxy}"
  mkdir -p "$wrap"
  printf 'module kuberos.local/build/coredns\n\ngo %s\n\nrequire %s %s\n' \
    "$go_line" "$mod" "$COREDNS_VERSION" >"$wrap/go.mod.new"
  mv -f "$wrap/go.mod.new" "$wrap/go.mod"
  cat >"$wrap/main.go" <<'GO'
// CoreDNS with the plugins of a cluster's Corefile only: the real-node tier's and kubeadm's (prometheus, forward,
// loop, reload, loadbalance), in the order of CoreDNS's own plugin.cfg.
package main

import (
	"github.com/coredns/coredns/core/dnsserver"
	_ "github.com/coredns/coredns/plugin/bind"
	_ "github.com/coredns/coredns/plugin/cache"
	_ "github.com/coredns/coredns/plugin/errors"
	_ "github.com/coredns/coredns/plugin/forward"
	_ "github.com/coredns/coredns/plugin/health"
	_ "github.com/coredns/coredns/plugin/hosts"
	_ "github.com/coredns/coredns/plugin/kubernetes"
	_ "github.com/coredns/coredns/plugin/loadbalance"
	_ "github.com/coredns/coredns/plugin/log"
	_ "github.com/coredns/coredns/plugin/loop"
	_ "github.com/coredns/coredns/plugin/metrics"
	_ "github.com/coredns/coredns/plugin/ready"
	_ "github.com/coredns/coredns/plugin/reload"
	"github.com/coredns/coredns/coremain"
)

func init() {
	dnsserver.Directives = []string{
		"reload", "bind", "ready", "health", "prometheus", "errors", "log", "loadbalance", "cache", "hosts", "kubernetes",
		"loop", "forward",
	}
}

func main() { coremain.Run() }
GO
  STEP="downloading modules for CoreDNS $COREDNS_VERSION"
  log "$STEP..."
  with_progress "$STEP" -- in_dir "$wrap" run_logged "$wrap.download.log" "$GO" mod tidy \
    || die "module download/resolution failed for CoreDNS $COREDNS_VERSION (log: $wrap.download.log)"
  log "modules ready ($(downloads_in "$wrap.download.log"))"
  record_time "coredns modules (resolve+download)" $((SECONDS - t0))
  local t1=$SECONDS out
  out=$(mktemp -d "$BIN_DIR/.build-coredns.XXXXXX"); TMP_DIRS+=("$out")
  STEP="building CoreDNS $COREDNS_VERSION"
  log "building CoreDNS $COREDNS_VERSION ($(index_of coredns)/$TOTAL)..."
  BUILD_LOG="$wrap.build.log" PACKAGES_TOTAL=""
  with_progress --about "$(about coredns)" --status packages_compiled "$STEP" -- \
      in_dir "$wrap" run_logged "$BUILD_LOG" "$GO" build -v -mod=mod -p "$BUILD_JOBS" -trimpath -ldflags "-s -w" \
      -o "$out/coredns" . \
    || die "go build failed for CoreDNS $COREDNS_VERSION (log: $BUILD_LOG)"
  install_binary coredns "$out/coredns"
  record_time "coredns build" $((SECONDS - t1))
}

build_kubernetes
build_etcd
build_kwok
build_coredns
STEP="finishing"

# --- summary -------------------------------------------------------------------

print_summary 9
log "versions: kubernetes $KUBERNETES_VERSION, etcd $ETCD_VERSION (with etcdctl, etcdutl), kwok $KWOK_VERSION, coredns $COREDNS_VERSION; total wall time $(fmt_secs $((SECONDS - T_START)))"
