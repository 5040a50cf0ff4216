#!/usr/bin/env bash
# Build Cilium's programs (the agent, the generic operator and the CNI plugin) and the reference loopback CNI
# plugin Cilium's image ships, from the Go module proxy only, with the ordinary `go` client, for a site (the lab)
# that builds its own Cilium images instead of pulling quay.io/cilium/cilium and quay.io/cilium/operator-generic.
#
# github.com/cilium/cilium carries two replace lines in its go.mod (metallb, controller-tools), so `go install`
# refuses it: the programs are built in a small wrapper module (under the cache's work/ directory) that requires
# cilium at CILIUM_VERSION and repeats those replace lines.
#
# Binaries land in the same cache as build-binaries.sh, keyed by version:
#   ${KUBEROS_CACHE_DIR:-$HOME/.cache/kuberos}/bin/<program>-<version>
# and share its Go module and build caches (go/mod, go/build). Run `--help` for options.
# Every long step prints a line at least every 30 s (KUBEROS_PROGRESS_INTERVAL) and its time when it ends.
set -euo pipefail

SCRIPT_NAME=$(basename "$0")
SCRIPT_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
# shellcheck source=SCRIPTDIR/progress.sh
source "$SCRIPT_DIR/progress.sh"
# shellcheck source=SCRIPTDIR/go-build.sh
source "$SCRIPT_DIR/go-build.sh"

CILIUM_MODULE=github.com/cilium/cilium
CNI_PLUGINS_MODULE=github.com/containernetworking/plugins
# What the built agent and operator report after the release: the build's patch level (see "The patch" below).
BUILD_LABEL=kuberos-1

usage() {
  cat <<EOF
Usage: $SCRIPT_NAME [--print-paths] [--help]

Build Cilium's agent, operator and CNI plugin from the Go module proxy into a version-keyed cache. Programs
already in the cache (and reporting the expected version) are not rebuilt.

Programs (cache name -> path in upstream's images):
  cilium-agent-<version>             quay.io/cilium/cilium            /usr/bin/cilium-agent
  cilium-operator-generic-<version>  quay.io/cilium/operator-generic  /usr/bin/cilium-operator-generic
  cilium-cni-<version>               quay.io/cilium/cilium            /opt/cni/bin/cilium-cni
  cni-loopback-<cni version>         quay.io/cilium/cilium            /cni/loopback

Options:
  --print-paths   Do not build; print name=path for each cached binary and exit
                  (exit 1, with a message on stderr, if any is missing).
                  Same as KUBEROS_PRINT_PATHS=1.
  -h, --help      Show this help.

Environment (defaults in brackets):
  CILIUM_VERSION         $CILIUM_MODULE release on the Go module proxy      [v1.15.19]
  CNI_PLUGINS_VERSION    $CNI_PLUGINS_MODULE release (Cilium 1.15 ships v1.6.0)    [v1.6.0]
  KUBEROS_CACHE_DIR      cache root                                     [\$HOME/.cache/kuberos]
  KUBEROS_BUILD_JOBS     go build -p value                                              [2]
  KUBEROS_PROGRESS_INTERVAL  seconds between progress lines of a long step              [30]
  GO                     go command                 [go on PATH, else /usr/local/go/bin/go]
  GOPROXY, GOSUMDB, GOTOOLCHAIN are honoured (GOTOOLCHAIN defaults to local).

Layout under the cache root:
  bin/<program>-<version>     the binaries
  go/mod, go/build            GOMODCACHE and GOCACHE (shared with build-binaries.sh)
  work/cilium-<version>/      the wrapper module and the build logs

The programs are built with CGO_ENABLED=0, as upstream builds them. The agent compiles its datapath (the C sources
under bpf/ of the same module) with clang when it starts: the image carries them and Debian's clang. One file is
patched in a copy of the module (work/cilium-<version>/src, the wrapper's replace target): a kernel without loadable
modules has no /proc/modules, which the 1.15 agent otherwise refuses to start without; the programs report
"<version> $BUILD_LABEL".
EOF
}

CILIUM_VERSION=${CILIUM_VERSION:-v1.15.19}
CNI_PLUGINS_VERSION=${CNI_PLUGINS_VERSION:-v1.6.0}
BUILD_JOBS=${KUBEROS_BUILD_JOBS:-2}
PRINT_PATHS=${KUBEROS_PRINT_PATHS:-0}

go_build_args "$@"

[[ $CILIUM_VERSION =~ ^v1\.[0-9]+\.[0-9]+$ ]] || die "CILIUM_VERSION must look like v1.15.19, got '$CILIUM_VERSION'"
[[ $CNI_PLUGINS_VERSION =~ ^v[0-9]+\.[0-9]+\.[0-9]+$ ]] \
  || die "CNI_PLUGINS_VERSION must look like v1.6.0, got '$CNI_PLUGINS_VERSION'"

# Cilium's programs: cache name -> package in the module (one go build each, sharing the build cache).
CILIUM_PROGRAMS=(cilium-agent cilium-operator-generic cilium-cni)
declare -A CILIUM_PKG=(
  [cilium-agent]=daemon
  [cilium-operator-generic]=operator
  [cilium-cni]=plugins/cilium-cni
)
PROGRAMS=("${CILIUM_PROGRAMS[@]}" cni-loopback)

version_of() { if [[ $1 == cni-* ]]; then echo "$CNI_PLUGINS_VERSION"; else echo "$CILIUM_VERSION"; fi; }
path_of() { echo "$BIN_DIR/$1-$(version_of "$1")"; }
import_path_of() {
  if [[ $1 == cni-* ]]; then echo "$CNI_PLUGINS_MODULE/plugins/main/${1#cni-}"; else echo "$CILIUM_MODULE/${CILIUM_PKG[$1]}"; fi
}

# Succeeds if binary $2 is program $1 (by its embedded build information) at the expected version.
binary_ok() {
  local name=$1 file=$2 info out
  [[ -f $file && -x $file ]] || return 1
  info=$("$GO" version -m "$file" 2>/dev/null) || return 1
  grep -qxF "$(printf '\tpath\t%s' "$(import_path_of "$name")")" <<<"$info" || return 1
  case $name in
    cilium-agent | cilium-operator-generic)
      out=$(timeout 60 "$file" --version 2>&1) || return 1
      [[ $out == *" ${CILIUM_VERSION#v} $BUILD_LABEL "* ]] ;;
    # The plugin prints its version only inside a CNI call; the module it was built from says it.
    cilium-cni)
      awk -v m="$CILIUM_MODULE" -v v="$CILIUM_VERSION" '($1 == "mod" || $1 == "dep") && $2 == m && $3 == v { f = 1 }
             END { exit !f }' <<<"$info" ;;
    # Run without CNI_COMMAND a reference plugin prints "CNI <name> plugin <version>" (and exits non-zero).
    cni-*)
      out=$(timeout 60 env -i "$file" 2>&1 </dev/null || true)
      [[ $out == *"CNI ${name#cni-} plugin $CNI_PLUGINS_VERSION"* ]] ;;
  esac
}

GO_BUILD_EXTRA_FLAGS="-buildvcs=false"
go_build_setup

log "cache: $CACHE_DIR ($("$GO" version | cut -d' ' -f3-), GOTOOLCHAIN=$GOTOOLCHAIN, -p $BUILD_JOBS)"
log "versions: cilium $CILIUM_VERSION ($CILIUM_MODULE, Go module proxy), CNI plugins $CNI_PLUGINS_VERSION"

collect_todo

# How long a step takes with cold caches on 2 cores, as measured on 2026-12-06 (the agent 3m18s-3m46s beside other
# work); shown with its progress lines.
about() {
  local when="on 2 free cores with cold caches"
  case $1 in
    cilium-modules) echo "about 30 s $when" ;;
    cilium) echo "the agent about 3-4 min $when, the others seconds" ;;
    cni-plugins) echo "about 10 s $when" ;;
  esac
}

wanted() { local p; for p in "${TODO[@]}"; do [[ $p == "$1" ]] && return 0; done; return 1; }

install_binary() {
  local name=$1 built=$2
  STEP="checking $name"
  binary_ok "$name" "$built" \
    || die "$name built at $built but is not $(import_path_of "$name") $(version_of "$name"): $("$GO" version -m "$built" 2>&1 | head -3)"
  mv -f "$built" "$(path_of "$name")"
}

# --- Cilium ----------------------------------------------------------------------

build_cilium() {
  local todo=() p
  for p in "${CILIUM_PROGRAMS[@]}"; do wanted "$p" && todo+=("$p"); done
  ((${#todo[@]})) || return 0

  local t0=$SECONDS tree="$WORK_DIR/cilium-$CILIUM_VERSION" json dir pkgs=() replaces
  STEP="downloading $CILIUM_MODULE@$CILIUM_VERSION"
  log "$STEP..."
  json=$("$GO" mod download -json "$CILIUM_MODULE@$CILIUM_VERSION" 2>&1) \
    || die "cannot download $CILIUM_MODULE@$CILIUM_VERSION from ${GOPROXY:-the Go module proxy}: $json"
  dir=$(sed -n 's/^[[:space:]]*"Dir": "\(.*\)",\{0,1\}$/\1/p' <<<"$json")
  [[ -n $dir && -f $dir/go.mod ]] || die "go mod download gave no module directory for $CILIUM_MODULE@$CILIUM_VERSION: $json"

  # The wrapper module: cilium required at the release, with the replace lines of cilium's own go.mod.
  STEP="writing the wrapper module"
  replaces=$(awk '/^replace \($/ { inside = 1; next } inside && /^\)$/ { inside = 0 } inside && /=>/ { print }
                  /^replace [^(]/ { sub(/^replace /, ""); print }' "$dir/go.mod")
  mkdir -p "$tree"
  rm -f "$tree/go.sum"
  {
    echo "module kuberos.local/cilium-build"
    echo
    echo "go $(awk '$1 == "go" { print $2; exit }' "$dir/go.mod")"
    echo
    echo "require $CILIUM_MODULE $CILIUM_VERSION"
    if [[ -n $replaces ]]; then
      echo
      echo "replace ("
      # shellcheck disable=SC2001  # a tab at the start of every line of the list
      sed 's/^[[:space:]]*/\t/' <<<"$replaces"
      echo ")"
    fi
  } >"$tree/go.mod"
  for p in "${todo[@]}"; do pkgs+=("$CILIUM_MODULE/${CILIUM_PKG[$p]}"); done

  STEP="downloading modules for ${todo[*]} $CILIUM_VERSION"
  log "$STEP..."
  with_progress --about "$(about cilium-modules)" "$STEP" -- \
      in_dir "$tree" run_logged "$tree/download.log" "$GO" list -mod=mod -tags ipam_provider_operator -deps "${pkgs[@]}" \
    || die "module download/resolution failed for Cilium $CILIUM_VERSION (log: $tree/download.log)"
  log "modules ready ($(downloads_in "$tree/download.log"))"
  record_time "cilium modules (resolve+download)" $((SECONDS - t0))

  # Where upstream's Makefile.defs stamps the version; the datapath hash keys the agent's compiled templates.
  local ldflags="-s -w" datapath
  datapath=$(cd "$dir" && find bpf -type f | LC_ALL=C sort | xargs cat | sha256sum | cut -d' ' -f1)
  ldflags+=" -X '$CILIUM_MODULE/pkg/version.ciliumVersion=${CILIUM_VERSION#v} $BUILD_LABEL'"
  ldflags+=" -X $CILIUM_MODULE/pkg/datapath/loader.DatapathSHA256=$datapath"

  # The patch: a kernel built without loadable modules (CONFIG_MODULES unset, as this machine's) has no
  # /proc/modules, and Cilium 1.15's agent refuses to start without it (1.20 no longer reads it). The build takes a
  # copy of the module (the wrapper's replace line points at it; the Go module cache is never modified) with one
  # change: a missing /proc/modules reads as no module loaded (every module such a kernel has is built in). A site's
  # kernel, which has /proc/modules, never takes that path.
  local src="$tree/src" modules="pkg/datapath/linux/modules/modules_linux.go"
  STEP="copying $CILIUM_MODULE@$CILIUM_VERSION to $src and patching $modules"
  grep -qF 'fModules, err := os.Open(loadedModulesFilepath)' "$dir/$modules" \
    || die "$dir/$modules has no os.Open(loadedModulesFilepath): the patch does not fit Cilium $CILIUM_VERSION"
  rm -rf "$src.new" "$src"
  TMP_DIRS+=("$src.new")
  cp -R "$dir/." "$src.new/"
  chmod -R u+w "$src.new"
  awk '{ print } /fModules, err := os.Open\(loadedModulesFilepath\)/ {
         print "\tif errors.Is(err, os.ErrNotExist) {"
         print "\t\treturn nil, nil // no loadable modules: no /proc/modules (kuberos build patch)"
         print "\t}"
       }' "$dir/$modules" >"$src.new/$modules"
  mv "$src.new" "$src"
  printf '\nreplace %s => ./src\n' "$CILIUM_MODULE" >>"$tree/go.mod"

  local t1=$SECONDS out
  out=$(mktemp -d "$BIN_DIR/.build-cilium.XXXXXX"); TMP_DIRS+=("$out")
  STEP="building ${todo[*]} $CILIUM_VERSION"
  log "$STEP (one go build each, sharing the build cache)..."
  BUILD_LOG="$tree/build.log" PACKAGES_TOTAL=$(packages_in "$tree/download.log")
  # osusergo as upstream; ipam_provider_operator makes the operator the generic one (cilium-operator-generic).
  for p in "${todo[@]}"; do
    with_progress --about "$(about cilium "${todo[*]}")" --status packages_compiled "$STEP: $p" -- \
        in_dir "$tree" run_logged "$BUILD_LOG" "$GO" build -v -mod=mod -p "$BUILD_JOBS" -trimpath \
        -tags osusergo,ipam_provider_operator -ldflags "$ldflags" -o "$out/$p" "$CILIUM_MODULE/${CILIUM_PKG[$p]}" \
      || die "go build failed for $p $CILIUM_VERSION (log: $BUILD_LOG)"
    install_binary "$p" "$out/$p"
  done
  record_time "cilium build (${#todo[@]} programs)" $((SECONDS - t1))
}

# --- the loopback CNI plugin -----------------------------------------------------

# What upstream's cilium image also ships (/cni/loopback, installed on the node when it has none).
build_loopback() {
  wanted cni-loopback || return 0
  local t0=$SECONDS out
  out=$(mktemp -d "$BIN_DIR/.build-cni.XXXXXX"); TMP_DIRS+=("$out")
  STEP="building the loopback CNI plugin $CNI_PLUGINS_VERSION"
  log "$STEP (go install, download included)..."
  BUILD_LOG="$WORK_DIR/cni-loopback-$CNI_PLUGINS_VERSION.log" PACKAGES_TOTAL=""
  with_progress --about "$(about cni-plugins)" --status packages_compiled "$STEP" -- \
      run_logged "$BUILD_LOG" env GOBIN="$out" "$GO" install -v -p "$BUILD_JOBS" -trimpath \
      -ldflags "-s -w -X $CNI_PLUGINS_MODULE/pkg/utils/buildversion.BuildVersion=$CNI_PLUGINS_VERSION" \
      "$CNI_PLUGINS_MODULE/plugins/main/loopback@$CNI_PLUGINS_VERSION" \
    || die "go install failed for $CNI_PLUGINS_MODULE loopback @$CNI_PLUGINS_VERSION (log: $BUILD_LOG)"
  install_binary cni-loopback "$out/loopback"
  record_time "CNI loopback plugin (download+build)" $((SECONDS - t0))
}

build_cilium
build_loopback
STEP="finishing"

# --- summary -------------------------------------------------------------------

print_summary 10
log "versions: cilium $CILIUM_VERSION, CNI plugins $CNI_PLUGINS_VERSION; total wall time $(fmt_secs $((SECONDS - T_START)))"
