#!/usr/bin/env bash
# Render procedural training scenes with Mitsuba's CUDA/OptiX variant (an NVIDIA GPU), several processes
# at once, one data-set folder per scene: OUT/s<seed>. Scene loading and kernel compilation are per
# process and mostly CPU work, so many processes keep one GPU busy (16 on an H100: ~24 s per 256x256
# scene each, 9 input levels and a 2048-spp reference). Train on them with data.root set to one folder
# and data.extra_roots to the others (this script prints that list), e.g. configs/unet_fast.yaml's recipe.
#
# usage: scripts/gpu_data.sh OUT FIRST_SEED N_SCENES [PROCESSES] [RESOLUTION]
#   env: PYTHON (default: python), KPCN_MITSUBA_VARIANT (default: cuda_ad_rgb), SPP, REF_SPP
set -euo pipefail
if [ $# -lt 3 ]; then sed -n '2,10p' "$0"; exit 2; fi
out=$1; first=$2; n=$3; procs=${4:-16}; res=${5:-256}
spp=${SPP:-"2 4 8 16 32 64 128 256 512"}; ref=${REF_SPP:-2048}
export KPCN_MITSUBA_VARIANT=${KPCN_MITSUBA_VARIANT:-cuda_ad_rgb}
export OMP_NUM_THREADS=1  # many processes: one thread each for the CPU-side work
mkdir -p "$out"
seq "$first" $((first + n - 1)) | xargs -P "$procs" -I{} \
  "${PYTHON:-python}" -m kpcn.render dataset --out "$out/s{}" --scenes 1 --first-seed {} \
  --spp $spp --ref-spp "$ref" --resolution "$res" "$res" >"$out/render.log" 2>&1 || {
  echo "some renders failed: see $out/render.log" >&2; exit 1; }
roots=$(for s in $(seq "$first" $((first + n - 1))); do echo "$out/s$s"; done)
echo "data.root=$(echo "$roots" | head -1)"
echo "data.extra_roots=[$(echo "$roots" | tail -n +2 | paste -sd, -)]"
