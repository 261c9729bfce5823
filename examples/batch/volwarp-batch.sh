#!/usr/bin/env bash
# Reprocess every scan of an input folder through the batch Makefile; made for cron.
#
#   volwarp-batch.sh [-C DIR] [-j JOBS] [MAKE_VARIABLE=value ...]
#
# - Takes a lock (flock) so two runs never overlap: a second run exits 75 (EX_TEMPFAIL)
#   at once, touching nothing.
# - Logs every step with a time stamp to $LOG (default DIR/logs/batch.log) and to stderr.
# - Keeps going past a bad scan (make -k); each scan's outputs are atomic, so a failed
#   scan leaves no partial file and the other scans' outputs are intact.
# - Ends with one summary line and exits 1 when any scan failed, 0 otherwise. A missing
#   input folder, or one holding no scan (an unmounted share), is a failure too (exit 1).
# - Relative IN=, OUT= and SPEC= are the caller's (as for any command), not the folder's.
# - Re-running with nothing changed does no work and changes no file (make's dependencies).
set -uo pipefail

DIR=$(cd "$(dirname "$0")" && pwd)
JOBS=2
while getopts "C:j:" opt; do
  case $opt in
    C) DIR=$(cd "$OPTARG" && pwd) ;;
    j) JOBS=$OPTARG ;;
    *) echo "usage: $0 [-C DIR] [-j JOBS] [VAR=value ...]" >&2; exit 2 ;;
  esac
done
shift $((OPTIND - 1))

# Relative IN/OUT/SPEC (arguments, or the environment make also reads) are the caller's:
# make runs in $DIR, so pass them on absolute. Left out, the Makefile's defaults (in $DIR).
abs() { case $1 in /*) printf '%s' "$1" ;; *) printf '%s/%s' "$PWD" "$1" ;; esac; }
args=()
IN_GIVEN=${IN:-}
IN_ABS=""
for var in IN OUT SPEC; do
  if [ -n "${!var:-}" ]; then args+=("$var=$(abs "${!var}")"); fi
done
for a in "$@"; do
  case $a in
    IN=*) IN_GIVEN=${a#IN=}; args+=("IN=$(abs "${a#IN=}")") ;;
    OUT=*) args+=("OUT=$(abs "${a#OUT=}")") ;;
    SPEC=*) args+=("SPEC=$(abs "${a#SPEC=}")") ;;
    *) args+=("$a") ;;
  esac
done
set -- "${args[@]+"${args[@]}"}"

LOG=${LOG:-$DIR/logs/batch.log}
LOCK=${LOCK:-$DIR/.batch.lock}
mkdir -p "$(dirname "$LOG")"

exec 9>"$LOCK"
if ! flock -n 9; then
  echo "volwarp-batch: another run holds $LOCK; not starting" >&2
  exit 75
fi

stamp() { while IFS= read -r line; do printf '%s %s\n' "$(date -u +%Y-%m-%dT%H:%M:%SZ)" "$line"; done; }

fail_summary() {  # one summary line for a run that could not start; exit 1
  echo "volwarp-batch: $1" | stamp | tee -a "$LOG" >&2
  echo "volwarp-batch: $1"
  exit 1
}

# A given input folder must exist (cron on an unmounted share must not report success).
if [ -n "$IN_GIVEN" ]; then
  IN_ABS=$(abs "$IN_GIVEN")
  [ -d "$IN_ABS" ] || fail_summary "input folder $IN_ABS does not exist or is not a folder (not mounted?): 0 scans, nothing done"
fi

{
  echo "volwarp-batch: start in $DIR ($*)"
  make --no-print-directory -C "$DIR" -k -j "$JOBS" all "$@" 2>&1
  echo "volwarp-batch: make exited $?"
} | stamp | tee -a "$LOG" >&2

# One line per scan from the Makefile: "ok NAME" or "failed NAME".
summary=$(make --no-print-directory -s -C "$DIR" status "$@" 2>/dev/null)
total=$(grep -c . <<<"$summary")
if [ "$total" -eq 0 ]; then
  fail_summary "no scan found in the input folder${IN_ABS:+ $IN_ABS} (empty or not mounted?): 0 scans, nothing done"
fi
failed=$(grep '^failed ' <<<"$summary" | cut -d' ' -f2- | tr '\n' ' ')
nfailed=$(grep -c '^failed ' <<<"$summary")
line="volwarp-batch: $total scans, $((total - nfailed)) ok, $nfailed failed${failed:+: $failed}"
echo "$line" | stamp | tee -a "$LOG" >&2
echo "$line"
[ "$nfailed" -eq 0 ]
