#!/usr/bin/env bash
# Progress for long steps: run a command, print a line every KUBEROS_PROGRESS_INTERVAL seconds (30) while it
# runs, and one when it ends with its time, so a first build or install is never silent for long.
#
#   source progress.sh
#   with_progress [--about TEXT] [--status FUNCTION] WHAT -- COMMAND [ARG...]
#
# prints, on stdout:
#   [17:02:41]   still building kube-apiserver v1.34.4 ... 1m30s elapsed (about 6 min on 2 cores; 812/2750 packages)
#   [17:08:02] done building kube-apiserver v1.34.4 in 5m21s
# and returns COMMAND's status ("failed building ... after 5m21s" instead of "done" when it is not 0).
# --status names a function whose output is added to every progress line (how far the step is).
# Run as a program, `progress.sh [--about TEXT] WHAT -- COMMAND...` does the same for one command.

progress_time() { printf '%dm%02ds' $(($1 / 60)) $(($1 % 60)); }

with_progress() {
  local about="" status="" what
  while [[ ${1:-} == --* ]]; do
    case $1 in
      --about) about=$2 ;;
      --status) status=$2 ;;
      *) echo "with_progress: unknown option $1" >&2; return 2 ;;
    esac
    shift 2
  done
  what=$1
  shift
  [[ ${1:-} == -- ]] && shift
  local interval=${KUBEROS_PROGRESS_INTERVAL:-30} started=$SECONDS caller=$BASHPID ticker rc=0
  (
    # The ticker ends with the command (killed below) or, if the caller dies first, at its next tick. Its
    # sleep writes nowhere, so a killed ticker never holds the caller's output pipe open.
    while sleep "$interval" >/dev/null 2>&1 && kill -0 "$caller" 2>/dev/null; do
      local extra=$about
      [[ -n $status ]] && extra+="${extra:+; }$("$status" 2>/dev/null)"
      printf '[%s]   still %s ... %s elapsed%s\n' "$(date +%H:%M:%S)" "$what" \
        "$(progress_time $((SECONDS - started)))" "${extra:+ ($extra)}"
    done
  ) &
  ticker=$!
  "$@" || rc=$?
  kill "$ticker" 2>/dev/null || true
  wait "$ticker" 2>/dev/null || true
  if ((rc == 0)); then
    printf '[%s] done %s in %s\n' "$(date +%H:%M:%S)" "$what" "$(progress_time $((SECONDS - started)))"
  else
    printf '[%s] failed %s after %s (exit %d)\n' "$(date +%H:%M:%S)" "$what" "$(progress_time $((SECONDS - started)))" "$rc"
  fi
  return "$rc"
}

if [[ ${BASH_SOURCE[0]} == "$0" ]]; then
  set -euo pipefail
  if (($# < 2)); then
    echo "usage: $(basename "$0") [--about TEXT] WHAT -- COMMAND [ARG...]" >&2
    exit 2
  fi
  with_progress "$@"
fi
