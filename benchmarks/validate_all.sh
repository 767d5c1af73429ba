#!/usr/bin/env bash
# Every configuration of the study (S=4 10 Hz 20 dBm, S=2 10 Hz 20 dBm, S=4 20 Hz 20 dBm, S=4 10 Hz 23 dBm, each at
# 0.1/0.2/0.3 veh/m) against the analytical model and the authors' Veins curves, with the simplified procedures
# (validate's base, highway-legacy) and with every standard procedure but in-band emission (docs/validation.md).
#
#   OUT=/tmp/validation_all WORKERS=16 SEEDS="1 2 3 4 5 6 7 8" SUBFRAMES=5000 benchmarks/validate_all.sh
#
# GRIDS picks the grids (default all three): simplified, standard, and model, the simplified base run under the
# analytical model's stated assumptions (validate --assumptions model: uniform choice, Step 2 alone with
# probability alpha(CBR), 0.1 dB threshold steps, each interferer alone; docs/validation.md), e.g.
#   GRIDS=model OUT=/tmp/validation_all WORKERS=16 SEEDS="1 2 3 4 5 6 7 8" SUBFRAMES=4000 benchmarks/validate_all.sh
# The model grid runs the numpy chunk (each interferer alone): 64 s against 37 s wall for the simplified grid here
# (2 seeds x 1500 subframes, 2 workers on the 2-core machine), about 1.75x.
#
# Cost measured on the 2-core machine (2 workers, shared): 110 CPU-s (simplified) and 193 CPU-s (standard) for
# 2 seeds x 1000 subframes of all 12 (configuration, density) pairs; a run's fixed part (warm-up) is about half of
# a 1000-subframe run. So about seeds x (18 + 37 x subframes/1000) CPU-s simplified and seeds x (32 + 65 x
# subframes/1000) standard: 8 seeds x 5000 subframes ~ 1600 + 2850 CPU-s, about 5 min wall on 16 workers.
set -euo pipefail
OUT=${OUT:-/tmp/validation_all}
WORKERS=${WORKERS:-16}
SEEDS=${SEEDS:-1 2 3 4 5 6 7 8}
SUBFRAMES=${SUBFRAMES:-5000}
PY=${PY:-.venv/bin/cv2x-marl}
GRIDS=${GRIDS:-simplified standard model}
tables=""
for grid in $GRIDS; do
    case "$grid" in
    simplified) extra=() ;;
    standard)
        extra=(--set sps.reservation_signalling=standard --set sps.reselection_timing=per_ue
            --set sps.sci_decoding=sinr --set sps.sci_gates_pssch=true
            --set link.per_interpolation=log --set channel.shadowing_correlation=pair_distance) ;;
    model) extra=(--assumptions model) ;;
    *) echo "GRIDS: unknown grid '$grid' (simplified, standard, model)" >&2; exit 2 ;;
    esac
    # shellcheck disable=SC2086
    $PY validate --out "$OUT/$grid" --overwrite --study --workers "$WORKERS" --seeds $SEEDS --subframes "$SUBFRAMES" \
        "${extra[@]}"
    tables="$tables $OUT/$grid/grid.md"
done
echo "tables:$tables"
