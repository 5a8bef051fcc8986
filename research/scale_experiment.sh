#!/usr/bin/env bash
# Table 2 and the Fig. 7 physics-weight runs at a chosen scale (issue 24), from the CLIs alone.
#
#   SIZE=256 NTRAIN=2000 EPOCHS=4 bash research/scale_experiment.sh runs/scale256   # GPU
#   SIZE=32 NTRAIN=16 NTEST=4 EPOCHS=1 PRESET=tiny bash research/scale_experiment.sh /tmp/s
#   SEEDS="0 1 2" CONCURRENT=12 STOP_AT=500 ... # 3 training seeds, 12 runs at once on one GPU
#
# 1. `ekdun make-dataset` (virtual bench, source-side dense model) and `psfkit fit-eigen` of
#    its grid (the measured seed; reused if OUT/measured.npz exists); a one-PSF seed
#    (Kv = Kh = Kbase of the measured fit). The dataset's operator oracle is fitted
#    (`python -m research.oracle DATA --write-dataset`) only where it is compared against
#    (COMPARE=1 without ORACLE); WRITE_ORACLE=1 or 0 overrides that.
# 2. Runs in priority order: Table 2 (measured seed: SCHEDULES x SEEDS), Fig. 7 (one-PSF seed,
#    last-2, kernel parameterisation x --physics-weight for each of F7_PARAMS x LAMBDAS) and
#    the measured seed (last-2, MEASURED_PARAMS x MEASURED_LAMBDAS); Fig. 7 runs use the
#    training seeds F7_SEEDS (default: the first of SEEDS). ABSORB_SEEDS adds, for those
#    training seeds, the learned half of research/unet_absorption.py: base only with the kernel
#    file ORACLE_SI and last-2 with ORACLE_EK, kernels frozen (--kernel-lr-scale 0).
#    With RESUME=1 a run whose folder holds a checkpoint continues it to EPOCHS (`ekdun train --resume`: a second call on the
#    same warm machine). CONCURRENT runs share the device at once (12 runs at batch 8 trained
#    at 138 images/s together on an H200). Sequentially, a run that would overrun DEADLINE_S seconds is
#    skipped; with STOP_AT, training still going at STOP_AT seconds is stopped and each run
#    is evaluated at its last finished epoch (checkpoints are written every epoch; the epoch
#    is in log.csv and eval/results.json).
# 3. `ekdun eval` of every run on the test split (PSNR, SSIM, inference time), and
#    `psfkit compare` of every learned kernel file against the measured fit and against the
#    operator oracle (ORACLE, default DATA/oracle/paper_source.npz), and of the measured fit.
# Results: OUT/summary.json (+ OUT/eval/, OUT/compare-*/ and each run's log.csv).
set -uo pipefail
OUT=${1:?usage: scale_experiment.sh OUT}
SIZE=${SIZE:-256}; NTRAIN=${NTRAIN:-2000}; NTEST=${NTEST:-64}; PHOTONS=${PHOTONS:-20000}
GRID_FRAMES=${GRID_FRAMES:-1}
EPOCHS=${EPOCHS:-4}; BATCH=${BATCH:-8}; PRESET=${PRESET:-paper}; LR=${LR:-5e-4}
# run lists: unset = the default, empty = none
LAMBDAS=${LAMBDAS-"10 0 1"}; SCHEDULES=${SCHEDULES-"last-2 base all"}
F7_PARAMS=${F7_PARAMS-free}; MEASURED_LAMBDAS=${MEASURED_LAMBDAS-}
MEASURED_PARAMS=${MEASURED_PARAMS:-free}; RESUME=${RESUME:-0}
ABSORB_SEEDS=${ABSORB_SEEDS-}
if [[ -n "$ABSORB_SEEDS" ]]; then
    : "${ORACLE_SI:?ABSORB_SEEDS needs ORACLE_SI (the SI oracle as Kbase = Kv = Kh, paper basis)}"
    : "${ORACLE_EK:?ABSORB_SEEDS needs ORACLE_EK (the EK oracle, paper basis)}"
fi
DEADLINE_S=${DEADLINE_S:-100000}; SEEDS=${SEEDS:-${SEED:-0}}
CONCURRENT=${CONCURRENT:-1}; STOP_AT=${STOP_AT:-0}; RUN_THREADS=${RUN_THREADS:-}
COMPARE=${COMPARE:-1}   # 0: no psfkit compare here (on a lent GPU: compare the kernels later)
# The dataset's operator oracle only where it is compared against: at 256² and 2000 pairs its fit
# (on the CPU) outlasted 8 minutes on a lent H200 before any training began
if [[ -z ${WRITE_ORACLE+set} ]]; then
    WRITE_ORACLE=0
    (( COMPARE )) && [[ -z ${ORACLE:-} ]] && WRITE_ORACLE=1
fi
PY=${PYTHON:-python3}
# research/ is not installed: python -m research.* from this checkout, wherever we run
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
start=$(date +%s)
elapsed() { echo $(( $(date +%s) - start )); }
mkdir -p "$OUT"
log() { echo "[$(elapsed) s] $*" | tee -a "$OUT/progress.log"; }
DATA="$OUT/data"
log "dataset ${SIZE}x${SIZE}, ${NTRAIN} train / ${NTEST} test, photons ${PHOTONS}$( (( WRITE_ORACLE )) && echo ' (with the oracle)')"
$PY -m ekdun.cli make-dataset "$DATA" --sensor "$SIZE" "$SIZE" --n-train "$NTRAIN" \
    --n-test "$NTEST" --photons "$PHOTONS" --grid-frames "$GRID_FRAMES" --quiet \
    || { log "make-dataset failed"; exit 1; }
if (( WRITE_ORACLE )); then
    PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}" $PY -m research.oracle "$DATA" --write-dataset \
        --quiet || { log "oracle failed"; exit 1; }
fi
if [[ -f "$OUT/measured.npz" ]]; then
    log "measured seed: $OUT/measured.npz (given)"
else
    log "fit-eigen (source side)"
    $PY -m psfkit.cli fit-eigen "$DATA/grid" --out "$OUT/measured.npz" --convention source \
        --quiet >/dev/null || { log "fit-eigen failed"; exit 1; }
fi
$PY - "$OUT/measured.npz" "$OUT/one_psf.npz" <<'PY' || { log "one-psf seed failed"; exit 1; }
import sys
from dataclasses import replace
from psfkit.forward.kernelfile import load_kernels, save_kernels
model = load_kernels(sys.argv[1])
k = model.kernels.copy()
k[1:] = k[:1]                      # Kv = Kh = Kbase: the network starts from one PSF
save_kernels(sys.argv[2], replace(model, kernels=k))
PY

# Priority order: Table 2 seed by seed, then Fig. 7 (so that a deadline cuts the tail)
read -r -a seeds <<<"$SEEDS"
F7_SEEDS=${F7_SEEDS:-${seeds[0]}}
runs=()
for seed in "${seeds[@]}"; do
    for s in $SCHEDULES; do
        runs+=("t2-$s-s$seed|--kernels $OUT/measured.npz --schedule $s --seed $seed")
    done
done
add_f7() {   # start seed_file params lambdas training_seed: last-2 runs, params x lambdas
    local p l
    for p in $3; do
        for l in $4; do
            runs+=("f7-$1-$p-l$l-s$5|--kernels $2 --schedule last-2 --kernel-param $p --physics-weight $l --seed $5")
        done
    done
}
for t in $F7_SEEDS; do
    add_f7 onepsf "$OUT/one_psf.npz" "$F7_PARAMS" "$LAMBDAS" "$t"
    add_f7 measured "$OUT/measured.npz" "$MEASURED_PARAMS" "$MEASURED_LAMBDAS" "$t"
done
# U-Net absorption (research/unet_absorption.py's learned half, concurrently): the physics frozen at
# the SI oracle (base only) and at the EK oracle (last-2), for the training seeds ABSORB_SEEDS
for t in $ABSORB_SEEDS; do
    runs+=("ab-base-si-s$t|--kernels $ORACLE_SI --schedule base --kernel-lr-scale 0 --seed $t")
    runs+=("ab-last-2-ek-s$t|--kernels $ORACLE_EK --schedule last-2 --kernel-lr-scale 0 --seed $t")
done
thread_flag=()
[[ -n "$RUN_THREADS" ]] && thread_flag=(--threads "$RUN_THREADS")
train_one() {   # name flags: one training run, its own log; stopped at STOP_AT
    local name=$1 flags=$2 budget=() resume=() left=$(( STOP_AT - $(elapsed) ))
    (( RESUME )) && [[ -f "$OUT/$name/checkpoint.pt" ]] && resume=(--resume)
    if (( STOP_AT > 0 )); then
        (( left > 0 )) || { log "skip $name: the time budget is spent"; return 124; }
        budget=(timeout --signal=TERM "$left")
    fi
    # the research knobs of the Fig. 7 runs: `ekdun train` with research/kernel_models.py
    local cmd=($PY -m ekdun.cli train)
    [[ $name == f7-* ]] && cmd=(env "PYTHONPATH=$REPO${PYTHONPATH:+:$PYTHONPATH}" $PY -m research.kernel_models)
    # shellcheck disable=SC2086
    "${budget[@]}" "${cmd[@]}" "$DATA" "$OUT/$name" $flags --preset "$PRESET" \
        --epochs "$EPOCHS" --batch-size "$BATCH" --lr "$LR" "${thread_flag[@]}" "${resume[@]}" \
        --quiet >>"$OUT/train-$name.log" 2>&1
    local rc=$?
    (( STOP_AT > 0 && rc == 124 )) && log "$name: stopped at ${STOP_AT} s"
    return $rc
}
per_run=0
pids=()
running() {   # training jobs still running
    local n=0 pid
    for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && n=$((n + 1)); done
    echo "$n"
}
for entry in "${runs[@]}"; do
    name=${entry%%|*}; flags=${entry#*|}
    if (( CONCURRENT <= 1 && per_run > 0 && $(elapsed) + per_run > DEADLINE_S )); then
        log "skip $name: would end after the deadline"; continue
    fi
    while (( $(running) >= CONCURRENT )); do sleep 2; done
    log "train $name: $flags"
    if (( CONCURRENT <= 1 )); then
        t0=$(date +%s)
        if train_one "$name" "$flags"; then per_run=$(( $(date +%s) - t0 )); fi
        log "$name ended after $(( $(date +%s) - t0 )) s: $(tail -n 1 "$OUT/$name/log.csv" 2>/dev/null)"
    else
        ( train_one "$name" "$flags"; log "$name ended (rc $?): $(tail -n 1 "$OUT/$name/log.csv" 2>/dev/null)" ) &
        pids+=($!)
    fi
done
(( ${#pids[@]} )) && wait "${pids[@]}"
done_runs=()
for entry in "${runs[@]}"; do
    name=${entry%%|*}
    [[ -f "$OUT/$name/checkpoint.pt" ]] && done_runs+=("$OUT/$name")
done
if (( ${#done_runs[@]} == 0 )); then log "no run finished"; exit 1; fi
log "eval ${#done_runs[@]} runs"
$PY -m ekdun.cli eval "${done_runs[@]}" --data "$DATA" --out "$OUT/eval" --overwrite \
    >>"$OUT/eval.log" 2>&1 || log "eval failed (see eval.log)"
ORACLE=${ORACLE:-$DATA/oracle/paper_source.npz}   # the dataset's operator oracle (above)
compared=()
(( COMPARE )) && compared=("${done_runs[@]}")
if (( COMPARE )) && [[ -f "$ORACLE" ]]; then
    $PY -m psfkit.cli compare "$OUT/measured.npz" "$ORACLE" --out "$OUT/oracle-measured" \
        --overwrite --quiet >>"$OUT/compare.log" 2>&1 || log "compare measured vs oracle failed"
fi
for run in "${compared[@]}"; do
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
