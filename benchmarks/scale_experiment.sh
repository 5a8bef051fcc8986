#!/usr/bin/env bash
# Table 2 and the Fig. 7 physics-weight runs at a chosen scale (issue 24), from the CLIs alone.
#
#   SIZE=256 NTRAIN=2000 EPOCHS=4 bash benchmarks/scale_experiment.sh runs/scale256   # GPU
#   SIZE=32 NTRAIN=16 NTEST=4 EPOCHS=1 PRESET=tiny bash benchmarks/scale_experiment.sh /tmp/s
#
# 1. `ekdun make-dataset` (virtual bench, source-side dense model) and `psfkit fit-eigen` of
#    its grid (the measured seed); a one-PSF seed (Kv = Kh = Kbase of the measured fit).
# 2. Runs, alternating, in priority order (a run that would overrun DEADLINE_S seconds is
#    skipped and logged): Table 2 (measured seed: SCHEDULES) and Fig. 7 (one-PSF seed, free
#    kernels, last-2, --physics-weight for each value of LAMBDAS).
# 3. `ekdun eval` of every finished run on the test split (PSNR, SSIM, inference time), and
#    `psfkit compare` of every learned kernel file against the measured fit and against the
#    dataset's operator oracle (DATA/oracle/paper_source.npz), and of the measured fit too.
# Results: OUT/summary.json (+ OUT/eval/, OUT/compare-*/ and each run's log.csv).
set -uo pipefail
OUT=${1:?usage: scale_experiment.sh OUT}
SIZE=${SIZE:-256}; NTRAIN=${NTRAIN:-2000}; NTEST=${NTEST:-64}; PHOTONS=${PHOTONS:-20000}
EPOCHS=${EPOCHS:-4}; BATCH=${BATCH:-8}; PRESET=${PRESET:-paper}; LR=${LR:-5e-4}
LAMBDAS=${LAMBDAS:-"10 0 1"}; SCHEDULES=${SCHEDULES:-"last-2 base all"}
DEADLINE_S=${DEADLINE_S:-100000}; SEED=${SEED:-0}
PY=${PYTHON:-python3}
start=$(date +%s)
elapsed() { echo $(( $(date +%s) - start )); }
mkdir -p "$OUT"
log() { echo "[$(elapsed) s] $*" | tee -a "$OUT/progress.log"; }

DATA="$OUT/data"
log "dataset ${SIZE}x${SIZE}, ${NTRAIN} train / ${NTEST} test, photons ${PHOTONS}"
$PY -m ekdun.cli make-dataset "$DATA" --sensor "$SIZE" "$SIZE" --n-train "$NTRAIN" \
    --n-test "$NTEST" --photons "$PHOTONS" --quiet || { log "make-dataset failed"; exit 1; }
log "fit-eigen (source side)"
$PY -m psfkit.cli fit-eigen "$DATA/grid" --out "$OUT/measured.npz" --convention source \
    --quiet >/dev/null || { log "fit-eigen failed"; exit 1; }
$PY - "$OUT/measured.npz" "$OUT/one_psf.npz" <<'PY' || { log "one-psf seed failed"; exit 1; }
import sys
from dataclasses import replace
from psfkit.kernelfile import load_kernels, save_kernels
model = load_kernels(sys.argv[1])
k = model.kernels.copy()
k[1:] = k[:1]                      # Kv = Kh = Kbase: the network starts from one PSF
save_kernels(sys.argv[2], replace(model, kernels=k))
PY

# Table 2 and Fig. 7 runs alternate, so that a deadline cuts the tail of both lists alike
t2=(); f7=(); runs=()
for s in $SCHEDULES; do t2+=("t2-$s|--kernels $OUT/measured.npz --schedule $s"); done
for l in $LAMBDAS; do
    f7+=("f7-onepsf-free-l$l|--kernels $OUT/one_psf.npz --schedule last-2 --kernel-param free --physics-weight $l")
done
for ((i = 0; i < ${#t2[@]} || i < ${#f7[@]}; i++)); do
    (( i < ${#t2[@]} )) && runs+=("${t2[$i]}")
    (( i < ${#f7[@]} )) && runs+=("${f7[$i]}")
done
per_run=0
done_runs=()
for entry in "${runs[@]}"; do
    name=${entry%%|*}; flags=${entry#*|}
    if (( per_run > 0 && $(elapsed) + per_run > DEADLINE_S )); then
        log "skip $name: would end after the deadline (${DEADLINE_S} s)"; continue
    fi
    t0=$(date +%s)
    log "train $name: $flags"
    # shellcheck disable=SC2086
    if $PY -m ekdun.cli train "$DATA" "$OUT/$name" $flags --preset "$PRESET" \
        --epochs "$EPOCHS" --batch-size "$BATCH" --lr "$LR" --seed "$SEED" --quiet \
        >>"$OUT/train.log" 2>&1; then
        done_runs+=("$OUT/$name")
        per_run=$(( $(date +%s) - t0 ))
        log "done $name in ${per_run} s: $(tail -n 1 "$OUT/$name/log.csv")"
    else
        log "train $name failed (see train.log)"
    fi
done
if (( ${#done_runs[@]} == 0 )); then log "no run finished"; exit 1; fi
log "eval ${#done_runs[@]} runs"
$PY -m ekdun.cli eval "${done_runs[@]}" --data "$DATA" --out "$OUT/eval" --overwrite \
    >>"$OUT/eval.log" 2>&1 || log "eval failed (see eval.log)"
ORACLE="$DATA/oracle/paper_source.npz"     # written by make-dataset (operator oracle)
if [[ -f "$ORACLE" ]]; then
    $PY -m psfkit.cli compare "$OUT/measured.npz" "$ORACLE" --out "$OUT/oracle-measured" \
        --overwrite --quiet >>"$OUT/compare.log" 2>&1 || log "compare measured vs oracle failed"
fi
for run in "${done_runs[@]}"; do
    name=$(basename "$run")
    $PY -m psfkit.cli compare "$run/kernels_learned.npz" "$OUT/measured.npz" \
        --initial "$run/kernels_initial.npz" --out "$OUT/compare-$name" --overwrite --quiet \
        >>"$OUT/compare.log" 2>&1 || log "compare $name failed"
    if [[ -f "$ORACLE" ]]; then
        $PY -m psfkit.cli compare "$run/kernels_learned.npz" "$ORACLE" \
            --initial "$run/kernels_initial.npz" --out "$OUT/oracle-$name" --overwrite \
            --quiet >>"$OUT/compare.log" 2>&1 || log "compare $name vs oracle failed"
    fi
done
$PY - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
summary = {"runs": {}}
measured = out / "oracle-measured" / "compare.json"
if measured.is_file():
    summary["measured_vs_oracle"] = json.loads(measured.read_text()).get("headline")
for run in sorted(out.glob("*/log.csv")):
    name = run.parent.name
    rows = run.read_text().strip().splitlines()
    entry = {"last_epoch": rows[-1]}
    for key, folder in (("vs_measured", f"compare-{name}"), ("vs_oracle", f"oracle-{name}")):
        cmp_file = out / folder / "compare.json"
        if cmp_file.is_file():
            entry[key] = json.loads(cmp_file.read_text()).get("headline")
    summary["runs"][name] = entry
for f in ("table2.json", "table1.json", "results.json"):
    p = out / "eval" / f
    if p.is_file():
        summary[f] = json.loads(p.read_text())
(out / "summary.json").write_text(json.dumps(summary, indent=1))
PY
log "finished"
