#!/usr/bin/env bash
# Build Calico's programs (calico-node, the calico CNI plugin and its installer, kube-controllers and
# its check-status probe) and the reference CNI plugins Calico's CNI image ships (portmap, loopback,
# host-local, bandwidth, tuning) from Go sources, with the ordinary `go` client and the Go module proxy
# only, for a site that builds its own Calico images instead of pulling calico/node, calico/cni and
# calico/kube-controllers.
#
# The Go module proxy serves Calico's monorepo as one pseudo-version of the release-v3.28 branch, and its
# module zip lacks the nested api/ module (go.mod: replace github.com/projectcalico/api => ./api): the
# api/ tree comes from CALICO_API_TARBALL (`git archive <commit> api`), or the whole source from a
# checkout (CALICO_SOURCE_DIR). Either is copied to a writable work tree outside the repository.
#
# Binaries land in the same cache as build-binaries.sh, keyed by version:
#   ${KUBEROS_CACHE_DIR:-$HOME/.cache/kuberos}/bin/<program>-<version>
# and share its Go module and build caches (go/mod, go/build). Run `--help` for options.
# Every long step prints a line at least every 30 s (KUBEROS_PROGRESS_INTERVAL) and its time when it ends.
set -euo pipefail

SCRIPT_NAME=$(basename "$0")
SCRIPT_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
REPO_ROOT=$(cd "$SCRIPT_DIR/../../.." && pwd)
# shellcheck source=SCRIPTDIR/progress.sh
source "$SCRIPT_DIR/progress.sh"
# shellcheck source=SCRIPTDIR/go-build.sh
source "$SCRIPT_DIR/go-build.sh"

CALICO_MODULE=github.com/projectcalico/calico
CNI_PLUGINS_MODULE=github.com/containernetworking/plugins
DEFAULT_MODULE_VERSION=v1.11.0-cni-plugin.0.20250813170300-a0db560f0520
DEFAULT_LABEL=v3.28.4-11-ga0db560f05

usage() {
  cat <<EOF
Usage: $SCRIPT_NAME [--print-paths] [--help]

Build Calico's node, CNI and kube-controllers programs from Go sources (the Go module proxy plus
Calico's api/ tree, or a checkout) into a version-keyed cache. Programs already in the cache (and
reporting the expected version) are not rebuilt.

Programs (cache name -> path in upstream's images):
  calico-node-<label>              calico/node            /bin/calico-node (all of -felix, -confd, -init,
                                                          -startup, -allocate-tunnel-addrs, -monitor-addresses,
                                                          -monitor-token, -status-reporter, -felix-live, ...)
  calico-cni-<label>               calico/cni             /opt/cni/bin/calico and /opt/cni/bin/calico-ipam
                                                          (one program; it acts by the name it is run under)
  calico-cni-install-<label>       calico/cni             /opt/cni/bin/install (the install-cni init container)
  calico-kube-controllers-<label>  calico/kube-controllers /usr/bin/kube-controllers
  calico-check-status-<label>      calico/kube-controllers /usr/bin/check-status (its liveness/readiness probes)
  cni-<plugin>-<cni version>       calico/cni             /opt/cni/bin/<plugin>, for each of CNI_PLUGINS

Options:
  --print-paths   Do not build; print name=path for each cached binary and exit
                  (exit 1, with a message on stderr, if any is missing).
                  Same as KUBEROS_PRINT_PATHS=1.
  -h, --help      Show this help.

Environment (defaults in brackets):
  CALICO_MODULE_VERSION  $CALICO_MODULE version on the Go module proxy
                         [$DEFAULT_MODULE_VERSION]
                         (the release-v3.28 branch at a0db560f0520, v3.28.4 + 11 commits)
  CALICO_VERSION         version label: binary names and what the programs report
                         [$DEFAULT_LABEL, or \`git describe\` of CALICO_SOURCE_DIR]
  CALICO_API_TARBALL     Calico's api/ tree at the module's commit (\`git archive <commit> api\`)
                         [<repository>/../shared/third_party/calico-api-$DEFAULT_LABEL.tar.gz]
  CALICO_SOURCE_DIR      a checkout of https://github.com/projectcalico/calico (api/ included) to build
                         instead of the module and the tarball                         [unset]
  CNI_PLUGINS            reference CNI plugins to build ("" for none)
                         [portmap loopback host-local bandwidth tuning]
  CNI_PLUGINS_VERSION    $CNI_PLUGINS_MODULE release (Calico's go.mod pins v1.1.1) [v1.1.1]
  KUBEROS_CACHE_DIR      cache root                                     [\$HOME/.cache/kuberos]
  KUBEROS_BUILD_JOBS     go build -p value                                              [2]
  KUBEROS_PROGRESS_INTERVAL  seconds between progress lines of a long step              [30]
  GO                     go command                 [go on PATH, else /usr/local/go/bin/go]
  GOPROXY, GOSUMDB, GOTOOLCHAIN are honoured (GOTOOLCHAIN defaults to local).

Layout under the cache root:
  bin/<program>-<version>     the binaries
  go/mod, go/build            GOMODCACHE and GOCACHE (shared with build-binaries.sh)
  work/calico-<label>/        the writable source tree and the build logs

The binaries are built with CGO_ENABLED=0, as upstream builds them on architectures without cgo: Felix's
eBPF dataplane (libbpf, cgo) and the mountns helper of the mount-bpffs init container (cgo) are not
available; the iptables dataplane, VXLAN and everything else are.
EOF
}

CALICO_MODULE_VERSION=${CALICO_MODULE_VERSION:-$DEFAULT_MODULE_VERSION}
CALICO_API_TARBALL=${CALICO_API_TARBALL:-$REPO_ROOT/../shared/third_party/calico-api-$DEFAULT_LABEL.tar.gz}
CALICO_SOURCE_DIR=${CALICO_SOURCE_DIR:-}
CNI_PLUGINS=${CNI_PLUGINS-portmap loopback host-local bandwidth tuning}
CNI_PLUGINS_VERSION=${CNI_PLUGINS_VERSION:-v1.1.1}
BUILD_JOBS=${KUBEROS_BUILD_JOBS:-2}
PRINT_PATHS=${KUBEROS_PRINT_PATHS:-0}

while (($#)); do
  case $1 in
    --print-paths) PRINT_PATHS=1 ;;
    -h | --help) usage; exit 0 ;;
    *) echo "$SCRIPT_NAME: unknown argument: $1 (try --help)" >&2; exit 2 ;;
  esac
  shift
done

CACHE_DIR=${KUBEROS_CACHE_DIR:-${HOME:?HOME is not set}/.cache/kuberos}
[[ $CACHE_DIR == /* ]] || CACHE_DIR="$PWD/$CACHE_DIR"   # go needs absolute paths
BIN_DIR="$CACHE_DIR/bin"
WORK_DIR="$CACHE_DIR/work"

log() { printf '[%s] %s\n' "$(date +%H:%M:%S)" "$*"; }
die() { printf '[%s] %s: ERROR: %s\n' "$(date +%H:%M:%S)" "$SCRIPT_NAME" "$*" >&2; exit 1; }

# --- versions and programs ----------------------------------------------------

if [[ -n $CALICO_SOURCE_DIR ]]; then
  [[ $CALICO_SOURCE_DIR == /* ]] || CALICO_SOURCE_DIR="$PWD/$CALICO_SOURCE_DIR"
  grep -qx "module $CALICO_MODULE" "$CALICO_SOURCE_DIR/go.mod" 2>/dev/null \
    || die "CALICO_SOURCE_DIR=$CALICO_SOURCE_DIR is not a checkout of $CALICO_MODULE (no go.mod declaring it)"
  [[ -f $CALICO_SOURCE_DIR/api/go.mod ]] \
    || die "CALICO_SOURCE_DIR=$CALICO_SOURCE_DIR has no api/go.mod (the nested github.com/projectcalico/api module)"
  if [[ -z ${CALICO_VERSION:-} ]] && git -C "$CALICO_SOURCE_DIR" rev-parse --git-dir >/dev/null 2>&1; then
    CALICO_VERSION=$(git -C "$CALICO_SOURCE_DIR" describe --tags --dirty --always --abbrev=10 2>/dev/null || true)
  fi
else
  # A Go pseudo-version ends in .<yyyymmddhhmmss>-<12 hex of the commit>: its time and commit stamp the build.
  [[ $CALICO_MODULE_VERSION =~ ([0-9]{14})-([0-9a-f]{12})$ ]] \
    || die "CALICO_MODULE_VERSION must be a pseudo-version ending in <yyyymmddhhmmss>-<12 hex>, got '$CALICO_MODULE_VERSION'"
  MODULE_TIME=${BASH_REMATCH[1]}
  MODULE_COMMIT=${BASH_REMATCH[2]}
fi
CALICO_VERSION=${CALICO_VERSION:-$DEFAULT_LABEL}
[[ $CALICO_VERSION =~ ^[0-9A-Za-z][0-9A-Za-z._+-]*$ ]] \
  || die "CALICO_VERSION must be a version label such as $DEFAULT_LABEL, got '$CALICO_VERSION'"
[[ $CNI_PLUGINS_VERSION =~ ^v[0-9]+\.[0-9]+\.[0-9]+$ ]] \
  || die "CNI_PLUGINS_VERSION must look like v1.1.1, got '$CNI_PLUGINS_VERSION'"

# Calico's programs: cache name -> package in the monorepo (all built by one go build).
CALICO_PROGRAMS=(calico-node calico-cni calico-cni-install calico-kube-controllers calico-check-status)
declare -A CALICO_PKG=(
  [calico-node]=node/cmd/calico-node
  [calico-cni]=cni-plugin/cmd/calico
  [calico-cni-install]=cni-plugin/cmd/install
  [calico-kube-controllers]=kube-controllers/cmd/kube-controllers
  [calico-check-status]=kube-controllers/cmd/check-status
)
# Reference CNI plugins: name -> package in github.com/containernetworking/plugins.
cni_pkg_of() {
  case $1 in
    loopback | bridge | host-device | ipvlan | macvlan | ptp | vlan) echo "plugins/main/$1" ;;
    host-local | dhcp | static) echo "plugins/ipam/$1" ;;
    portmap | bandwidth | tuning | firewall | sbr | vrf) echo "plugins/meta/$1" ;;
    *) return 1 ;;
  esac
}
CNI_LIST=()
read -r -a CNI_LIST <<<"$CNI_PLUGINS"
PROGRAMS=("${CALICO_PROGRAMS[@]}")
for p in "${CNI_LIST[@]}"; do
  cni_pkg_of "$p" >/dev/null || die "CNI_PLUGINS: unknown plugin '$p' (one of loopback, host-local, portmap, bandwidth, tuning, ...)"
  PROGRAMS+=("cni-$p")
done

version_of() { if [[ $1 == cni-* ]]; then echo "$CNI_PLUGINS_VERSION"; else echo "$CALICO_VERSION"; fi; }
path_of() { echo "$BIN_DIR/$1-$(version_of "$1")"; }
import_path_of() {
  if [[ $1 == cni-* ]]; then echo "$CNI_PLUGINS_MODULE/$(cni_pkg_of "${1#cni-}")"; else echo "$CALICO_MODULE/${CALICO_PKG[$1]}"; fi
}

# Succeeds if binary $2 is program $1 (by its embedded build information) and reports the expected version.
binary_ok() {
  local name=$1 file=$2 info out dir rc=0
  [[ -f $file && -x $file ]] || return 1
  info=$("$GO" version -m "$file" 2>/dev/null) || return 1
  grep -qxF "$(printf '\tpath\t%s' "$(import_path_of "$name")")" <<<"$info" || return 1
  case $name in
    calico-node) out=$(timeout 60 "$file" -v 2>&1) || return 1 ;;
    calico-cni)
      # The plugin acts by the name it runs under: check both names upstream installs it as.
      dir=$(mktemp -d "$WORK_DIR/.check.XXXXXX")
      ln -s "$file" "$dir/calico"; ln -s "$file" "$dir/calico-ipam"
      out=$(timeout 60 "$dir/calico" -v 2>&1 && timeout 60 "$dir/calico-ipam" -v 2>&1) || rc=1
      rm -rf "$dir"
      ((rc == 0)) || return 1
      [[ $(sort -u <<<"$out") == "$CALICO_VERSION" ]] || return 1 ;;
    calico-kube-controllers) out=$(timeout 60 "$file" --version 2>&1) || return 1 ;;
    calico-check-status) out=$(timeout 60 "$file" -v 2>&1) || return 1 ;;
    # The installer has no version flag (run, it installs into /host/...), and -trimpath keeps -ldflags out of the
    # build information: the label set with -X must be among its strings.
    calico-cni-install) LC_ALL=C grep -qaF -- "$CALICO_VERSION" "$file" || return 1; out=$CALICO_VERSION ;;
    # Run without CNI_COMMAND a reference plugin prints "CNI <name> plugin <version>" (and exits non-zero).
    cni-*) awk -v m="$CNI_PLUGINS_MODULE" -v v="$CNI_PLUGINS_VERSION" '$1 == "mod" && $2 == m && $3 == v { f = 1 }
             END { exit !f }' <<<"$info" || return 1
           out=$(timeout 60 env -i "$file" 2>&1 </dev/null || true)
           [[ $out == *"CNI ${name#cni-} plugin $CNI_PLUGINS_VERSION"* ]] || return 1
           out=$CNI_PLUGINS_VERSION ;;
  esac
  grep -qxF "$(version_of "$name")" <<<"$out"
}

GO_BUILD_EXTRA_FLAGS="-buildvcs=false"
go_build_setup

log "cache: $CACHE_DIR ($("$GO" version | cut -d' ' -f3-), GOTOOLCHAIN=$GOTOOLCHAIN, -p $BUILD_JOBS)"
if [[ -n $CALICO_SOURCE_DIR ]]; then
  log "versions: calico $CALICO_VERSION (from $CALICO_SOURCE_DIR), CNI plugins $CNI_PLUGINS_VERSION"
else
  log "versions: calico $CALICO_VERSION ($CALICO_MODULE@$CALICO_MODULE_VERSION + $CALICO_API_TARBALL), CNI plugins $CNI_PLUGINS_VERSION"
fi

TODO=()
for p in "${PROGRAMS[@]}"; do
  if binary_ok "$p" "$(path_of "$p")"; then
    log "cached   $p $(version_of "$p") ($(index_of "$p")/$TOTAL): $(path_of "$p")"
  else
    TODO+=("$p")
  fi
done
# Run "$@" with its output in log file $1; on failure show the log's tail.
run_logged() {
  local logfile=$1 rc=0
  shift
  "$@" >"$logfile" 2>&1 || rc=$?
  if ((rc != 0)); then
    printf -- '--- last lines of %s ---\n' "$logfile" >&2
    tail -n 40 "$logfile" >&2
    printf -- '---\n' >&2
  fi
  return "$rc"
}
downloads_in() { local n; n=$(grep -c '^go: downloading' "$1" || true); echo "${n:-0} modules downloaded"; }
in_dir() { local dir=$1; shift; (cd "$dir" && "$@"); }

# The progress of a go build -v writing to $BUILD_LOG: packages compiled so far (of $PACKAGES_TOTAL, the
# packages `go list -deps` found, when known; fewer are compiled when the Go build cache has the others).
BUILD_LOG=/dev/null
PACKAGES_TOTAL=""
packages_compiled() {
  local n
  n=$(grep -vc '^go: ' "$BUILD_LOG" 2>/dev/null || true)
  echo "${n:-0}${PACKAGES_TOTAL:+ of $PACKAGES_TOTAL} packages compiled"
}
packages_in() { grep -vc '^go: ' "$1" || true; }

# How long a step takes with cold caches on 2 cores, as measured (2026-11-26: 28 s, 3m06s-4m06s, 7-12 s); shown
# with its progress lines.
# Other work on the machine makes it much longer.
about() {
  local when="on 2 free cores with cold caches"
  case $1 in
    calico-modules) echo "about 30 s $when" ;;
    calico) if [[ $2 == "${CALICO_PROGRAMS[*]}" ]]; then echo "about 3-4 min $when"; fi ;;
    cni-plugins) echo "about 10 s $when" ;;
  esac
}

wanted() { local p; for p in "${TODO[@]}"; do [[ $p == "$1" ]] && return 0; done; return 1; }

# Move freshly built $2 into place as program $1 after checking its version.
install_binary() {
  local name=$1 built=$2 dest
  dest=$(path_of "$name")
  STEP="checking $name"
  binary_ok "$name" "$built" \
    || die "$name built at $built but does not report version $(version_of "$name"): $("$GO" version -m "$built" 2>&1 | head -3)"
  mv -f "$built" "$dest"
}

# --- Calico ----------------------------------------------------------------------

# Fills $SRC (a fresh writable source tree), $REVISION and $BUILD_DATE.
SRC=""
REVISION=""
BUILD_DATE=""
prepare_source() {
  local tree="$WORK_DIR/calico-$CALICO_VERSION"
  SRC="$tree/src"
  mkdir -p "$tree"
  rm -rf "$SRC.new" "$SRC"
  TMP_DIRS+=("$SRC.new")
  if [[ -n $CALICO_SOURCE_DIR ]]; then
    STEP="copying $CALICO_SOURCE_DIR"
    log "$STEP to $SRC"
    mkdir -p "$SRC.new"
    tar -C "$CALICO_SOURCE_DIR" --exclude=.git -cf - . | tar -C "$SRC.new" -xf -
    if git -C "$CALICO_SOURCE_DIR" rev-parse --git-dir >/dev/null 2>&1; then
      REVISION=$(git -C "$CALICO_SOURCE_DIR" rev-parse HEAD)
      BUILD_DATE=$(git -C "$CALICO_SOURCE_DIR" show -s --format=%cd --date=format-local:%Y-%m-%dT%H:%M:%SZ HEAD 2>/dev/null \
        | head -1 || true)
      [[ -z $(git -C "$CALICO_SOURCE_DIR" status --porcelain 2>/dev/null | head -1) ]] || REVISION+="-dirty"
    else
      REVISION=unknown
    fi
    [[ -n $BUILD_DATE ]] || BUILD_DATE=$(date -u +%Y-%m-%dT%H:%M:%SZ)
  else
    STEP="checking CALICO_API_TARBALL"
    [[ -f $CALICO_API_TARBALL ]] \
      || die "Calico's api/ tree is missing: CALICO_API_TARBALL=$CALICO_API_TARBALL does not exist. The module proxy's \
zip of $CALICO_MODULE@$CALICO_MODULE_VERSION leaves out the nested api/ module; provide \`git archive $MODULE_COMMIT api\` \
of https://github.com/projectcalico/calico as that tarball, or set CALICO_SOURCE_DIR to a checkout of that commit"
    tar -tzf "$CALICO_API_TARBALL" api/go.mod >/dev/null 2>&1 \
      || die "CALICO_API_TARBALL=$CALICO_API_TARBALL is not a gzipped tar with api/go.mod (expected \`git archive <commit> api | gzip\`)"
    # git archive records its commit in the tar header: it must be the module's.
    if command -v git >/dev/null 2>&1; then
      REVISION=$(gzip -dc "$CALICO_API_TARBALL" | git get-tar-commit-id 2>/dev/null || true)
      if [[ -n $REVISION ]]; then
        [[ $REVISION == "$MODULE_COMMIT"* ]] \
          || die "CALICO_API_TARBALL=$CALICO_API_TARBALL is api/ of commit $REVISION, not of the module's commit $MODULE_COMMIT"
      fi
    fi
    [[ -n $REVISION ]] || REVISION=$MODULE_COMMIT
    BUILD_DATE="${MODULE_TIME:0:4}-${MODULE_TIME:4:2}-${MODULE_TIME:6:2}T${MODULE_TIME:8:2}:${MODULE_TIME:10:2}:${MODULE_TIME:12:2}Z"

    local t0=$SECONDS json dir
    STEP="downloading $CALICO_MODULE@$CALICO_MODULE_VERSION"
    log "$STEP..."
    json=$("$GO" mod download -json "$CALICO_MODULE@$CALICO_MODULE_VERSION" 2>&1) \
      || die "cannot download $CALICO_MODULE@$CALICO_MODULE_VERSION from ${GOPROXY:-the Go module proxy}: $json"
    dir=$(sed -n 's/^[[:space:]]*"Dir": "\(.*\)",\{0,1\}$/\1/p' <<<"$json")
    [[ -n $dir && -f $dir/go.mod ]] || die "go mod download gave no module directory for $CALICO_MODULE@$CALICO_MODULE_VERSION: $json"
    STEP="copying $CALICO_MODULE@$CALICO_MODULE_VERSION and $(basename "$CALICO_API_TARBALL")"
    log "$STEP to $SRC"
    mkdir -p "$SRC.new"
    cp -R "$dir/." "$SRC.new/"
    chmod -R u+w "$SRC.new"
    [[ ! -e $SRC.new/api ]] || die "$CALICO_MODULE@$CALICO_MODULE_VERSION already has an api/ directory: is CALICO_API_TARBALL needed?"
    tar -xzf "$CALICO_API_TARBALL" -C "$SRC.new" api
    record_time "calico source (module download + copy)" $((SECONDS - t0))
  fi
  grep -q '=>[[:space:]]*\./api' "$SRC.new/go.mod" \
    || log "note: go.mod has no 'replace github.com/projectcalico/api => ./api' (api/ is unused)"
  mv "$SRC.new" "$SRC"
}

build_calico() {
  local todo=() p
  for p in "${CALICO_PROGRAMS[@]}"; do wanted "$p" && todo+=("$p"); done
  ((${#todo[@]})) || return 0

  prepare_source
  local t0=$SECONDS tree="$WORK_DIR/calico-$CALICO_VERSION" pkgs=()
  for p in "${todo[@]}"; do pkgs+=("./${CALICO_PKG[$p]}"); done

  STEP="downloading modules for ${todo[*]} $CALICO_VERSION"
  log "$STEP..."
  with_progress --about "$(about calico-modules)" "$STEP" -- \
      in_dir "$SRC" run_logged "$tree/download.log" "$GO" list -mod=mod -deps "${pkgs[@]}" \
    || die "module download/resolution failed for Calico $CALICO_VERSION (log: $tree/download.log)"
  log "modules ready ($(downloads_in "$tree/download.log"))"
  record_time "calico modules (resolve+download)" $((SECONDS - t0))

  # Where upstream's Makefiles stamp the version (node/Makefile, cni-plugin/Makefile, kube-controllers/Makefile):
  # calico-node -v prints startup.VERSION; Felix, the status reporter and the tunnel address allocator report
  # buildinfo.*; the CNI plugin, its installer, kube-controllers and check-status print main.VERSION.
  local ldflags="-s -w"
  ldflags+=" -X $CALICO_MODULE/node/pkg/lifecycle/startup.VERSION=$CALICO_VERSION"
  ldflags+=" -X $CALICO_MODULE/node/buildinfo.GitVersion=$CALICO_VERSION"
  ldflags+=" -X $CALICO_MODULE/node/buildinfo.BuildDate=$BUILD_DATE"
  ldflags+=" -X $CALICO_MODULE/node/buildinfo.GitRevision=$REVISION"
  ldflags+=" -X main.VERSION=$CALICO_VERSION"

  local t1=$SECONDS out first last
  out=$(mktemp -d "$BIN_DIR/.build-calico.XXXXXX"); TMP_DIRS+=("$out")
  first=$(index_of "${todo[0]}"); last=$(index_of "${todo[-1]}")
  STEP="building ${todo[*]} $CALICO_VERSION"
  log "building ${todo[*]} $CALICO_VERSION ($first-$last/$TOTAL, one go build)..."
  BUILD_LOG="$tree/build.log" PACKAGES_TOTAL=$(packages_in "$tree/download.log")
  with_progress --about "$(about calico "${todo[*]}")" --status packages_compiled "$STEP" -- \
      in_dir "$SRC" run_logged "$BUILD_LOG" "$GO" build -v -mod=mod -p "$BUILD_JOBS" -trimpath \
      -ldflags "$ldflags" -o "$out/" "${pkgs[@]}" \
    || die "go build failed for ${todo[*]} $CALICO_VERSION (log: $BUILD_LOG)"
  for p in "${todo[@]}"; do install_binary "$p" "$out/$(basename "${CALICO_PKG[$p]}")"; done
  record_time "calico build (${#todo[@]} programs, one go build)" $((SECONDS - t1))
}

# --- reference CNI plugins -------------------------------------------------------

# What upstream's calico/cni image also ships in /opt/cni/bin (and its installer copies to the host): the
# containernetworking plugins, built with `go install pkg@version` from their own go.mod.
build_cni_plugins() {
  local todo=() p
  for p in "${CNI_LIST[@]}"; do wanted "cni-$p" && todo+=("$p"); done
  ((${#todo[@]})) || return 0
  local t0=$SECONDS out pkgs=() first last
  for p in "${todo[@]}"; do pkgs+=("$CNI_PLUGINS_MODULE/$(cni_pkg_of "$p")@$CNI_PLUGINS_VERSION"); done
  out=$(mktemp -d "$BIN_DIR/.build-cni.XXXXXX"); TMP_DIRS+=("$out")
  first=$(index_of "cni-${todo[0]}"); last=$(index_of "cni-${todo[-1]}")
  STEP="building CNI plugins ${todo[*]} $CNI_PLUGINS_VERSION"
  log "$STEP ($first-$last/$TOTAL, go install, download included)..."
  BUILD_LOG="$WORK_DIR/cni-plugins-$CNI_PLUGINS_VERSION.log" PACKAGES_TOTAL=""
  with_progress --about "$(about cni-plugins)" --status packages_compiled "$STEP" -- \
      run_logged "$BUILD_LOG" env GOBIN="$out" "$GO" install -v -p "$BUILD_JOBS" -trimpath \
      -ldflags "-s -w -X $CNI_PLUGINS_MODULE/pkg/utils/buildversion.BuildVersion=$CNI_PLUGINS_VERSION" "${pkgs[@]}" \
    || die "go install failed for $CNI_PLUGINS_MODULE ${todo[*]} @$CNI_PLUGINS_VERSION (log: $BUILD_LOG)"
  for p in "${todo[@]}"; do install_binary "cni-$p" "$out/$p"; done
  record_time "CNI plugins (download+build, ${#todo[@]} plugins)" $((SECONDS - t0))
  log "CNI plugins: $(downloads_in "$BUILD_LOG")"
}

build_calico
build_cni_plugins
STEP="finishing"

# --- summary -------------------------------------------------------------------

log "summary:"
for p in "${PROGRAMS[@]}"; do
  binary_ok "$p" "$(path_of "$p")" || die "$p is not usable at $(path_of "$p") after the build"
  printf '  %-24s %-24s %s\n' "$p" "$(version_of "$p")" "$(path_of "$p")"
done
if ((${#TIME_ORDER[@]})); then
  log "step times:"
  for k in "${TIME_ORDER[@]}"; do printf '  %-60s %s\n' "$k" "$(fmt_secs "${TIMES[$k]}")"; done
else
  log "nothing to build: all ${#PROGRAMS[@]} programs were cached"
fi
log "versions: calico $CALICO_VERSION, CNI plugins $CNI_PLUGINS_VERSION; total wall time $(fmt_secs $((SECONDS - T_START)))"
