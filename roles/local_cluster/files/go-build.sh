# shellcheck shell=bash
# shellcheck disable=SC2034,SC2317  # its variables and functions are used by the scripts that source it
# What the Go build scripts (build-binaries.sh, build-cilium.sh, build-kube-score.sh) share, sourced by each: their
# arguments and cache folders, --print-paths, the Go environment (caches under $CACHE_DIR/go, CGO off, no workspace),
# one build at a time per cache (flock on $CACHE_DIR/.build.lock), the clean-up on exit, the step timings, the cache
# check (collect_todo), logged commands and progress, and the summary. Call go_build_args "$@", then go_build_setup
# once PROGRAMS and path_of are set (with_progress comes from progress.sh); GO_BUILD_EXTRA_FLAGS adds to GOFLAGS.

# The scripts' arguments (--print-paths, --help: the script's usage) and where the cache is: sets PRINT_PATHS,
# CACHE_DIR, BIN_DIR and WORK_DIR, and defines log and die.
go_build_args() {
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
}
log() { printf '[%s] %s\n' "$(date +%H:%M:%S)" "$*"; }
die() { printf '[%s] %s: ERROR: %s\n' "$(date +%H:%M:%S)" "$SCRIPT_NAME" "$*" >&2; exit 1; }

go_build_setup() {
  if [[ $PRINT_PATHS == 1 ]]; then
    missing=0
    for p in "${PROGRAMS[@]}"; do
      f=$(path_of "$p")
      if [[ -x $f ]]; then
        echo "$p=$f"
      else
        echo "$SCRIPT_NAME: missing $p: $f (run $SCRIPT_NAME to build it)" >&2
        missing=1
      fi
    done
    exit "$missing"
  fi

  # --- environment ----------------------------------------------------------------

  if [[ -z ${GO:-} ]]; then
    if command -v go >/dev/null 2>&1; then GO=go
    elif [[ -x /usr/local/go/bin/go ]]; then GO=/usr/local/go/bin/go
    else die "no go command found (set GO=/path/to/go)"
    fi
  fi
  "$GO" version >/dev/null 2>&1 || die "'$GO version' does not run"

  mkdir -p "$BIN_DIR" "$WORK_DIR" "$CACHE_DIR/go/mod" "$CACHE_DIR/go/build"
  export GOPATH="$CACHE_DIR/go"
  export GOMODCACHE="$CACHE_DIR/go/mod"
  export GOCACHE="$CACHE_DIR/go/build"
  export GOFLAGS="-modcacherw${GO_BUILD_EXTRA_FLAGS:+ $GO_BUILD_EXTRA_FLAGS}"  # module cache deletable by rm -rf / CI cache
  export GOTOOLCHAIN="${GOTOOLCHAIN:-local}"
  export GOWORK=off
  export CGO_ENABLED=0
  unset GOBIN
  cd "$WORK_DIR" || exit 1               # never run go inside some other module

  # One build at a time per cache directory.
  if command -v flock >/dev/null 2>&1; then
    exec 9>"$CACHE_DIR/.build.lock"
    flock -n 9 || with_progress "waiting for another build to release $CACHE_DIR/.build.lock" -- flock 9
  fi

  STEP="starting"
  TMP_DIRS=()
  # shellcheck disable=SC2317  # run by the EXIT trap
  on_exit() {
    local rc=$?
    local d
    for d in "${TMP_DIRS[@]}"; do rm -rf "$d"; done
    if ((rc != 0)); then
      printf '[%s] %s: FAILED (exit %d) while %s\n' "$(date +%H:%M:%S)" "$SCRIPT_NAME" "$rc" "$STEP" >&2
    fi
  }
  trap on_exit EXIT

  T_START=$SECONDS
  declare -gA TIMES=()      # step label -> seconds
  TIME_ORDER=()
  record_time() { TIMES[$1]=$2; TIME_ORDER+=("$1"); }
  fmt_secs() { printf '%dm%02ds' $(($1 / 60)) $(($1 % 60)); }

  TOTAL=${#PROGRAMS[@]}
  index_of() { local i; for i in "${!PROGRAMS[@]}"; do [[ ${PROGRAMS[$i]} == "$1" ]] && { echo $((i + 1)); return; }; done; }
}

# The programs of PROGRAMS that are not in the cache at the expected version (binary_ok): fills TODO.
collect_todo() {
  TODO=()
  local p
  for p in "${PROGRAMS[@]}"; do
    if binary_ok "$p" "$(path_of "$p")"; then
      log "cached   $p $(version_of "$p") ($(index_of "$p")/$TOTAL): $(path_of "$p")"
    else
      TODO+=("$p")
    fi
  done
}

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

# Every program usable at its path (or die), then the step times; $1: the width of the version column.
print_summary() {
  local p
  log "summary:"
  for p in "${PROGRAMS[@]}"; do
    binary_ok "$p" "$(path_of "$p")" || die "$p is not usable at $(path_of "$p") after the build"
    printf "  %-26s %-${1}s %s\n" "$p" "$(version_of "$p")" "$(path_of "$p")"
  done
  if ((${#TIME_ORDER[@]})); then
    log "step times:"
    for p in "${TIME_ORDER[@]}"; do printf '  %-60s %s\n' "$p" "$(fmt_secs "${TIMES[$p]}")"; done
  else
    log "nothing to build: all ${#PROGRAMS[@]} programs were cached"
  fi
}
