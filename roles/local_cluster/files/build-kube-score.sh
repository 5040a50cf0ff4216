#!/usr/bin/env bash
# Build kube-score (the Kubernetes manifest checker that tests/lint/test_kube_score.py runs over the manifests
# rendered from examples/*.yml) from its Go module, with the ordinary `go` client and the Go module proxy only
# (no release downloads).
#
# The binary lands in the same cache as build-binaries.sh, keyed by version:
#   ${KUBEROS_CACHE_DIR:-$HOME/.cache/kuberos}/bin/kube-score-<version>
# and shares its Go module and build caches (go/mod, go/build). Run `--help` for options.
# Every long step prints a line at least every 30 s (KUBEROS_PROGRESS_INTERVAL) and its time when it ends.
set -euo pipefail

SCRIPT_NAME=$(basename "$0")
# shellcheck source=SCRIPTDIR/progress.sh
source "$(dirname "${BASH_SOURCE[0]}")/progress.sh"
# shellcheck source=SCRIPTDIR/go-build.sh
source "$(dirname "${BASH_SOURCE[0]}")/go-build.sh"

KUBE_SCORE_MODULE=github.com/zegl/kube-score
KUBE_SCORE_PKG=$KUBE_SCORE_MODULE/cmd/kube-score

usage() {
  cat <<EOF
Usage: $SCRIPT_NAME [--print-paths] [--help]

Build kube-score ($KUBE_SCORE_PKG) from the Go module proxy into a version-keyed cache, for
the manifest lint of \`make test\` (tests/lint/test_kube_score.py). A binary already in the cache (and
answering \`kube-score version\` with the expected version) is not rebuilt.

Options:
  --print-paths   Do not build; print kube-score=path for the cached binary and exit
                  (exit 1, with a message on stderr, if it is missing).
                  Same as KUBEROS_PRINT_PATHS=1.
  -h, --help      Show this help.

Environment (defaults in brackets):
  KUBE_SCORE_VERSION   $KUBE_SCORE_MODULE release             [v1.20.0]
  KUBEROS_CACHE_DIR    cache root                  [\$HOME/.cache/kuberos]
  KUBEROS_BUILD_JOBS   go build -p value                      [2]
  KUBEROS_PROGRESS_INTERVAL  seconds between progress lines of a long step [30]
  GO                   go command                 [go on PATH, else /usr/local/go/bin/go]
  GOPROXY, GOSUMDB, GOTOOLCHAIN are honoured (GOTOOLCHAIN defaults to local).

Layout under the cache root:
  bin/kube-score-<version>   the binary
  go/mod, go/build           GOMODCACHE and GOCACHE (shared with build-binaries.sh)
  work/kube-score-<version>.log  the build log
EOF
}

KUBE_SCORE_VERSION=${KUBE_SCORE_VERSION:-v1.20.0}
BUILD_JOBS=${KUBEROS_BUILD_JOBS:-2}
PRINT_PATHS=${KUBEROS_PRINT_PATHS:-0}

go_build_args "$@"

# --- version and program --------------------------------------------------------

[[ $KUBE_SCORE_VERSION =~ ^v[0-9]+\.[0-9]+\.[0-9]+(-[0-9A-Za-z.]+)?$ ]] \
  || die "KUBE_SCORE_VERSION must look like v1.20.0, got '$KUBE_SCORE_VERSION'"

PROGRAMS=(kube-score)
version_of() { echo "$KUBE_SCORE_VERSION"; }
path_of() { echo "$BIN_DIR/$1-$(version_of "$1")"; }

# Succeeds if binary $2 runs and reports the expected version ("kube-score version: v1.20.0, commit: ..."; a build
# without the release's -X main.version says "development").
binary_ok() {
  local file=$2 out
  [[ -f $file && -x $file ]] || return 1
  out=$(timeout 60 "$file" version 2>&1) || return 1
  [[ $out == *"kube-score version: $KUBE_SCORE_VERSION,"* ]]
}

go_build_setup

log "cache: $CACHE_DIR ($("$GO" version | cut -d' ' -f3-), GOTOOLCHAIN=$GOTOOLCHAIN, -p $BUILD_JOBS)"
log "versions: kube-score $KUBE_SCORE_VERSION"

# The progress of a go install -v writing to $BUILD_LOG: packages compiled so far.
BUILD_LOG=/dev/null
packages_compiled() {
  local n
  n=$(grep -vc '^go: ' "$BUILD_LOG" 2>/dev/null || true)
  echo "${n:-0} packages compiled"
}

# How long the build takes on 2 cores, as measured (2026-11-28, beside other tests: load average 10 and more): with
# empty Go caches 3m50s, 52 s of it CPU (28 modules, 23 MB downloaded); with the Go caches of build-binaries.sh
# 1m04s (16 modules, 19 MB); with warm caches 10 s. Shown with its progress lines.
ABOUT="about 1-4 min on 2 cores with cold caches"

FILE=$(path_of kube-score)
if binary_ok kube-score "$FILE"; then
  log "cached   kube-score $KUBE_SCORE_VERSION (1/$TOTAL): $FILE"
  log "nothing to build: kube-score $KUBE_SCORE_VERSION was cached"
  exit 0
fi

# --- kube-score -------------------------------------------------------------------

t0=$SECONDS
STEP="resolving $KUBE_SCORE_MODULE@$KUBE_SCORE_VERSION"
log "$STEP"
# The release's publication time from the proxy stamps the build (upstream's goreleaser sets main.date).
BUILD_DATE=$("$GO" list -m -f '{{with .Time}}{{.UTC.Format "2006-01-02T15:04:05Z"}}{{end}}' \
  "$KUBE_SCORE_MODULE@$KUBE_SCORE_VERSION" 2>&1) \
  || die "cannot resolve $KUBE_SCORE_MODULE@$KUBE_SCORE_VERSION from ${GOPROXY:-the Go module proxy}: $BUILD_DATE"
[[ -n $BUILD_DATE ]] || BUILD_DATE=$(date -u +%Y-%m-%dT%H:%M:%SZ)

OUT=$(mktemp -d "$BIN_DIR/.build-kube-score.XXXXXX"); TMP_DIRS+=("$OUT")
STEP="building kube-score $KUBE_SCORE_VERSION"
log "building kube-score $KUBE_SCORE_VERSION (1/$TOTAL, go install, download included)..."
# go install pkg@version uses kube-score's own go.mod (it has no replace directives).
BUILD_LOG="$WORK_DIR/kube-score-$KUBE_SCORE_VERSION.log"
with_progress --about "$ABOUT" --status packages_compiled "$STEP" -- \
    run_logged "$BUILD_LOG" env GOBIN="$OUT" "$GO" install -v -p "$BUILD_JOBS" -trimpath \
    -ldflags "-s -w -X main.version=$KUBE_SCORE_VERSION -X main.date=$BUILD_DATE" "$KUBE_SCORE_PKG@$KUBE_SCORE_VERSION" \
  || die "go install failed for $KUBE_SCORE_PKG@$KUBE_SCORE_VERSION (log: $BUILD_LOG)"
STEP="checking kube-score"
binary_ok kube-score "$OUT/kube-score" \
  || die "kube-score built at $OUT/kube-score but does not report version $KUBE_SCORE_VERSION: \
$("$OUT/kube-score" version 2>&1 | head -3)"
mv -f "$OUT/kube-score" "$FILE"
record_time "kube-score (download+build)" $((SECONDS - t0))
log "kube-score: $(downloads_in "$BUILD_LOG")"
STEP="finishing"

# --- summary -------------------------------------------------------------------

log "summary:"
binary_ok kube-score "$FILE" || die "kube-score is not usable at $FILE after the build"
printf '  %-24s %-9s %s\n' kube-score "$KUBE_SCORE_VERSION" "$FILE"
log "step times:"
for k in "${TIME_ORDER[@]}"; do printf '  %-60s %s\n' "$k" "$(fmt_secs "${TIMES[$k]}")"; done
log "versions: kube-score $KUBE_SCORE_VERSION; total wall time $(fmt_secs $((SECONDS - T_START)))"
