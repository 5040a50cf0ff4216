# shellcheck shell=bash
# shellcheck disable=SC2034,SC2317  # its variables and functions are used by the scripts that source it
# What build-binaries.sh and build-cilium.sh share, sourced by both: --print-paths, the Go environment (caches under
# $CACHE_DIR/go, CGO off, no workspace), one build at a time per cache (flock on $CACHE_DIR/.build.lock), the clean-up
# on exit, and the step timings. Call go_build_setup after PROGRAMS, path_of, PRINT_PATHS, BIN_DIR, WORK_DIR and
# CACHE_DIR are set (and log, die, with_progress from progress.sh); GO_BUILD_EXTRA_FLAGS adds to GOFLAGS.

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
