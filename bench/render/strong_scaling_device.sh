#!/usr/bin/env bash
# bench_strong_scaling on a lent many-core machine (no network there), within a short lease.
# Here, in the checkout:  bash ../shared/bundle/make.sh .bundle   (nprt's wheel + what that
# machine lacks); there, from the checkout's root, with .bundle carried:
#   bash bench/render/strong_scaling_device.sh .bundle "forest:2,4,8" "city:8"
# Each SCENE:KS runs one `bench_strong_scaling --scenes SCENE --ks KS` (the 1-core reference
# first, then exact and proxy per K) into $OUT (default bench/results/device), one JSON each;
# a run cut short by the lease leaves strong_scaling_partial.json. nprt comes from the
# bundle's wheel, bench/ from this checkout. BYTE_SLACK=1.5 (say) runs them at that
# RenderSettings.byte_slack, its value in the results' tag. REF_RUNS (default 2) runs the
# reference that many times per scene, before and after the distributed rows (the ratios
# against their mean): one reference moved 13-20 % within a lease in session 16.
# CONTENTION_NS="1 8 9 16" (say) first runs bench_contention at those copy counts: how much
# CPU the machine itself adds to a render when that many run at once (one round each).
# THREADS=city:8 (say) then runs bench_shard_threads for that scene and K (both modes):
# the shards' CPU split by thread (the wavefront thread, Ray's Python and C++ threads).
# CARRIES=city:8 (say) then runs bench_step_hold for that scene and K (both modes), with and
# without carrying a step's leftover rays into the next step (remote.CARRY_RAYS), one round.
# PACK=FILE tars the results folder into FILE after each run. A lent machine hands back
# at most 8 files, so there: PACK=$OUT/res.tgz OUT=/tmp/res bash ... (in that order: the
# device's $OUT is expanded first); what a cut run left still comes back.
set -u
BUNDLE=$(cd "${1:?usage: strong_scaling_device.sh BUNDLE SCENE:K,K ...}" && pwd); shift
OUT=${OUT:-bench/results/device}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 RAY_USAGE_STATS_ENABLED=0
t0=$(date +%s)
bash "$BUNDLE/install.sh" || exit 1
export PYTHONPATH=/tmp/site:$PWD PATH=/tmp/site/bin:$PATH
echo "installed in $(( $(date +%s) - t0 )) s; nproc $(nproc); $(grep -m1 'model name' /proc/cpuinfo)"
lscpu | grep -E '^(Thread|Core|Socket|NUMA node\(s\)|L3)' || true
uptime
# Warm-up: compiles every numba kernel once (cached beside the installed modules), so no
# timed row pays the compile.
# Once per machine: a second call on the same lease finds /tmp/site/.warm.
if [ ! -f /tmp/site/.warm ]; then
  python3 -m bench.render.bench_strong_scaling --smoke --out "$OUT/warm" > "$OUT/warm.log" 2>&1 \
    || { echo "warm-up failed:"; tail -30 "$OUT/warm.log"; exit 1; }
  rm -rf "$OUT/warm"; touch /tmp/site/.warm
fi
echo "warm at $(( $(date +%s) - t0 )) s"
if [ -n "${CONTENTION_NS:-}" ]; then
  # shellcheck disable=SC2086
  python3 -m bench.render.bench_contention --ns $CONTENTION_NS --rounds 1 --no-readme \
    --out "$OUT" 2>&1 | tee -a "$OUT/contention.log"
  echo "contention done at $(( $(date +%s) - t0 )) s"
  if [ -n "${PACK:-}" ]; then tar -czf "$PACK" -C "$OUT" .; fi
fi
if [ -n "${THREADS:-}" ]; then
  python3 -m bench.render.bench_shard_threads --scenes "${THREADS%%:*}" --k "${THREADS#*:}" \
    --no-readme --out "$OUT" 2>&1 | grep -v -E '^\(|WARNING|INFO' | tee -a "$OUT/threads.log"
  echo "threads done at $(( $(date +%s) - t0 )) s"
  if [ -n "${PACK:-}" ]; then tar -czf "$PACK" -C "$OUT" .; fi
fi
if [ -n "${CARRIES:-}" ]; then
  python3 -m bench.render.bench_step_hold --scenes "${CARRIES%%:*}" --k "${CARRIES#*:}" \
    --holds 16384:8 --carries 0 1048576 --rounds 1 --no-readme --out "$OUT" 2>&1 \
    | grep -v -E '^\(|WARNING|INFO' | tee -a "$OUT/carries.log"
  echo "carries done at $(( $(date +%s) - t0 )) s"
  if [ -n "${PACK:-}" ]; then tar -czf "$PACK" -C "$OUT" .; fi
fi
for spec in "$@"; do
  scene=${spec%%:*}; ks=${spec#*:}; tag=$(nproc)core-$scene-${ks//,/_}${BYTE_SLACK:+-slack$BYTE_SLACK}
  # shellcheck disable=SC2086
  python3 -m bench.render.bench_strong_scaling --scenes "$scene" --ks ${ks//,/ } --no-readme \
    --out "$OUT" --tag "$tag" --ref-runs "${REF_RUNS:-2}" ${BYTE_SLACK:+--byte-slack "$BYTE_SLACK"} 2>&1 | grep -v -E '^\(|WARNING|INFO' | tee -a "$OUT/scaling.log"
  [ -f "$OUT/strong_scaling_$tag.json" ] && rm -f "$OUT/strong_scaling_partial.json"
  echo "$tag done at $(( $(date +%s) - t0 )) s"; uptime
  if [ -n "${PACK:-}" ]; then tar -czf "$PACK" -C "$OUT" .; fi
done
