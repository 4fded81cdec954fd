#!/bin/sh
# The same recordings through two echoloc installs; every output compared byte for byte.
#   benchmarks/compare_outputs.sh BEFORE_ECHOLOC AFTER_ECHOLOC [REAL_H5]
# e.g. a worktree of the old commit with its own .venv beside this one. REAL_H5 (a real
# CH101 recording, default ../shared/data/ch101-spiel/dev.h5) is calibrated on half its
# target positions and located on the other half.
set -e
BEFORE=$1; AFTER=$2
HERE=$(cd "$(dirname "$0")/.." && pwd)
REAL=${3:-$HERE/../shared/data/ch101-spiel/dev.h5}
WORK=$(mktemp -d)
"$BEFORE" simulate "$HERE/src/echoloc/scenes/random-1m3.toml" -o "$WORK/rf.h5" --frames 20 >/dev/null
"$BEFORE" simulate "$HERE/src/echoloc/scenes/random-1m3-six.toml" -o "$WORK/six.h5" --frames 10 >/dev/null
(cd "$WORK" && "$BEFORE" simulate ch101 -o "$WORK/env.h5" --frames 20 >/dev/null)
run() {  # run ECHOLOC OUTDIR
    E=$1; O=$2; mkdir -p "$O"
    for est in matched threshold leading-edge energy; do
        "$E" echoes "$WORK/rf.h5" --json --estimator $est > "$O/echoes_rf_$est.jsonl"
        "$E" locate "$WORK/rf.h5" --json --estimator $est > "$O/locate_rf_$est.jsonl"
    done
    "$E" locate "$WORK/rf.h5" --json --method backprojection --frames 3 > "$O/locate_rf_bp.jsonl"
    "$E" echoes "$WORK/env.h5" --json > "$O/echoes_env.jsonl"
    "$E" locate "$WORK/env.h5" --json > "$O/locate_env.jsonl"
    "$E" locate "$WORK/six.h5" --json > "$O/locate_six.jsonl"
    "$E" design --json > "$O/design.json"
    "$E" design --range-m 1.0 --path-error-m 0.002 --spacing-m 0.3 > "$O/design.txt"
    if [ -f "$REAL" ]; then
        "$E" calibrate "$REAL" --positions 0::2 -o "$O/cal.json" >/dev/null
        "$E" locate "$REAL" --json --calibration "$O/cal.json" --positions 1::2 > "$O/locate_real.jsonl"
    fi
}
run "$BEFORE" "$WORK/before"
run "$AFTER" "$WORK/after"
diff -r "$WORK/before" "$WORK/after" && echo "identical: $(ls "$WORK/after" | wc -l) outputs in $WORK"
