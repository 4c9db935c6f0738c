#!/usr/bin/env bash
# The detector families on a GPU machine (benchmarks/RESULTS.md "Detector families"): batch-1 / batch-32 forward
# throughput at each paper's input size, then each family's quickstart (1,000 steps on simulated scenes, clean test,
# small illusion suite), the seven runs side by side. Results land in $OUT (fps.jsonl, one run_<family>.tgz each).
#   OUT=/tmp/out bash benchmarks/families_gpu.sh                 # STEPS, CASES, TEST, FAMILIES shrink it for a dry run
set -u
OUT=${OUT:-/tmp/families_out}; mkdir -p "$OUT"
STEPS=${STEPS:-1000}; CASES=${CASES:-10}; TEST=${TEST:-100}; FAMILIES=${FAMILIES:-laneatt ufld bezierlanenet ganet scnn laneformer clrnet}
DEVICE=${DEVICE:-cuda}; REPEATS=${REPEATS:-20}; LIMIT=${LIMIT:-420}; WORKERS=${WORKERS:-3}
export PYTHONUNBUFFERED=1 WANDB_MODE=offline
python3 benchmarks/bench_families.py --device "$DEVICE" --families "$(echo $FAMILIES | tr ' ' ,)" --repeats "$REPEATS" --modes eager,graph \
    --json "$OUT/fps.jsonl" > "$OUT/fps.log" 2>&1
tail -8 "$OUT/fps.log"
accelerator=$([ "$DEVICE" = cuda ] && echo gpu || echo cpu)
mkdir -p /tmp/families_runs
for family in $FAMILIES; do
  experiment=quickstart; [ "$family" != laneatt ] && experiment=quickstart_$family
  run=/tmp/families_runs/$family
  ( timeout "$LIMIT" python3 -m lanevil_train experiment=$experiment trainer.accelerator=$accelerator \
      trainer.max_steps=$STEPS task.cases=$CASES data.test.num_scenes=$TEST data.num_workers=$WORKERS progress=plain \
      hydra.run.dir=$run > /tmp/families_runs/$family.log 2>&1; echo "exit $?" >> /tmp/families_runs/$family.log
    cp /tmp/families_runs/$family.log $run/ 2>/dev/null
    tar czf "$OUT/run_$family.tgz" --exclude='*.ckpt' --exclude='per_image.jsonl' -C /tmp/families_runs $family $family.log
  ) &
done
wait
for family in $FAMILIES; do echo "== $family"; grep -E "exit|Accuracy|Error|error" /tmp/families_runs/$family.log | tail -4; done
