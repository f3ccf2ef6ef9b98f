#!/usr/bin/env bash
# One short GPU lease (a bare machine, no network, one command of at most 10 minutes): render fresh procedural
# scenes with Mitsuba's CUDA variant (PROCS worker loops, none started after RENDER_S), then fine-tune the wide
# U-Net on them until BUDGET seconds after the start (BASE: the config whose model and losses it takes, default
# configs/unet_wide64n.yaml, the shipped default's recipe; INIT: the weights it starts from, default
# unet_kpcn:wide64n, the default's file; LR: the peak rate; SPP_MIX: data.spp_mix, the share of patches whose spp
# varies per pixel, default 0; EDGE: model.edge_upsample, the normal-guided blend, default 0.5 as the shipped default
# runs it, 0 bilinear; FULLRES: model.fullres_channels, a full-resolution decoder level added at the file's output
# and trained with the rest, default 0: none, as the shipped default). FIRST: the first scene seed; earlier leases rendered from
# 50001 (sixteenth session), 60001 (twenty-sixth and thirty-first) and 71001 (thirty-fifth): pass a fresh one.
# The step count follows the measured pace: a probe run to step PROBE, then --resume with the fitted
# train.stage2_steps (the one-cycle schedule ends in time). Weights,
# config and logs go to $OUT (model.safetensors, or model_partial.safetensors from the last checkpoint).
#
# The machine has PyTorch but not Mitsuba or OpenEXR: carry them as .gpu/site.tar.xz, built here once from the
# CPython 3.12 wheels (pip download --no-deps --only-binary=:all: --python-version 3.12 --platform
# manylinux_2_28_x86_64 mitsuba==3.9.1 drjit==1.5.0 OpenEXR==3.5.3; unzip them into one folder, drop the
# variants other than cuda_ad_rgb, the headers and the volume/curve/polarised plugins: 29 MB as xz), e.g.
#   BUDGET=520 RENDER_S=170 bash scripts/gpu_train.sh        (device run, carry: [".gpu"])
# The tree that travels (tracked files, .gpu) must stay under 64 MiB: with 47 MB of shipped weights it did not
# (eighteenth session), so the weights the run does not start from were moved out of the tree for the call; with
# unet_wide64a (nineteenth session) they are 70 MB, with unet_wide64s (twentieth) 79 MB, with unet_wide64b
# (twenty-second) 88 MB, with unet_wide64c (twenty-third) 97 MB: move every weights file but INIT's aside for the
# call, `bash scripts/gpu_weights.sh hold`
# (and `restore` after it).
# REF_FLOOR (a relMSE, e.g. 0.0015) gives each reference whose own noise adds more than that more samples, up to
# 16384 spp (python -m kpcn.render dataset --ref-floor-target).
# EXTRA="NAME=CONFIG ..." trains more models beside it on the same scenes, to the same deadline, each from its
# CONFIG's model and train sections (from scratch unless that config names train.init; its data.patch_size kept, its
# train.batch_size unless EXTRA_BATCH; peak rate EXTRA_LR, default 2e-4): weights, configs and logs go to $OUT/NAME/.
# They share the GPU and the cores with the main run, which then takes fewer steps (each pace is measured under load).
# Locally, as a dry run: PY=.venv/bin/python NO_SITE=1 KPCN_MITSUBA_VARIANT=llvm_ad_rgb RES=48 SPP="2 4" REF=16
#   PROCS=2 RENDER_S=30 BUDGET=300 BATCH=2 PATCH=32 W=/tmp/gt bash scripts/gpu_train.sh
set -u
T0=$(date +%s)
BUDGET=${BUDGET:-540}; RENDER_S=${RENDER_S:-180}; PROBE=${PROBE:-200}
PY=${PY:-python3}; RES=${RES:-256}; SPP=${SPP:-"2 4 8 16 32 64 128 256 512"}; REF=${REF:-2048}
PROCS=${PROCS:-16}; FIRST=${FIRST:-81001}; W=${W:-/tmp/g}; OUT=${OUT:-$W/out}
el() { echo $(( $(date +%s) - T0 )); }
# renders started before RENDER_S finish up to ~30 s after it, the store and the probe's first 100 steps take ~60 s
# more: a shorter lease trains nothing (twenty-sixth session: BUDGET=205 RENDER_S=65 stopped its probe at step 100)
[ "$BUDGET" -ge $((RENDER_S + 200)) ] || { echo "gpu_train: BUDGET=$BUDGET leaves no time to train after" \
  "RENDER_S=$RENDER_S (needs BUDGET >= RENDER_S + 200)" >&2; exit 2; }
mkdir -p "$W" "$OUT"
if [ -f .gpu/site.tar.xz ] && [ -z "${NO_SITE:-}" ]; then
  mkdir -p /tmp/site && tar xJf .gpu/site.tar.xz -C /tmp/site || exit 3
  export PYTHONPATH=/tmp/site:$PWD/src
fi
export PYTHONUNBUFFERED=1
$PY - <<'EOF' || exit 4
import os, mitsuba as mi, torch
mi.set_variant(os.environ.get("KPCN_MITSUBA_VARIANT", "cuda_ad_rgb"))
import OpenEXR, kpcn
print("mitsuba", mi.__version__, mi.variant(), "torch", torch.__version__,
      torch.cuda.get_device_name() if torch.cuda.is_available() else "no cuda", flush=True)
EOF
echo "setup done at $(el) s"

# 1. render: PROCS loops, worker i takes seeds FIRST+i, FIRST+i+PROCS, ... and starts none after RENDER_S
export KPCN_MITSUBA_VARIANT=${KPCN_MITSUBA_VARIANT:-cuda_ad_rgb} OMP_NUM_THREADS=1
mkdir -p "$W/d"
for i in $(seq 0 $((PROCS - 1))); do
  ( s=$((FIRST + i))
    while [ $(( $(date +%s) - T0 )) -lt "$RENDER_S" ]; do
      $PY -m kpcn.render dataset --out "$W/d/s$s" --scenes 1 --first-seed $s --spp $SPP --ref-spp $REF \
          --resolution $RES $RES ${REF_FLOOR:+--ref-floor-target $REF_FLOOR} >>"$W/d/render_$i.log" 2>&1 \
        || echo "render $s failed" >>"$W/d/failed.log"
      s=$((s + PROCS))
    done ) &
done
wait
unset OMP_NUM_THREADS
echo "render done at $(el) s"; cat "$W/d/failed.log" 2>/dev/null | head -3

# 2. the config: every complete scene, the first held out for validation
$PY - "$W" <<'EOF' || exit 5
import os, sys, yaml
from pathlib import Path
from kpcn.render import dataset_status
w = Path(sys.argv[1])
roots = sorted(str(p) for p in (w / "d").glob("s*") if dataset_status(p).complete)
print(len(roots), "complete scenes", flush=True)
base = yaml.safe_load(open(os.environ.get("BASE", "configs/unet_wide64n.yaml")))
d = base["data"]
d.update(root=roots[1], extra_roots=roots[2:], val_root=roots[0], store=str(w / "store"), workers=8,
         patch_size=int(os.environ.get("PATCH", 128)), converged_min_ref_spp=int(os.environ.get("REF", 2048)),
         spp_by_root={}, balance_spp=False,  # every fresh scene at every spp
         spp_mix=float(os.environ.get("SPP_MIX", 0)))
# the shipped default runs its blend guided by the normal (edge_upsample 0.5): train as it runs (EDGE=0: bilinear)
base["model"]["edge_upsample"] = float(os.environ.get("EDGE", 0.5))
# more full-resolution capacity where the 4-spp error against OIDN lies (the geometry's edges): FULLRES=16
base["model"]["fullres_channels"] = int(os.environ.get("FULLRES", 0))
base["train"].update(init=os.environ.get("INIT", "unet_kpcn:wide64n"), init_extend=True, init_reopen=[],
                     batch_size=int(os.environ.get("BATCH", 32)), stage2_lr=float(os.environ.get("LR", 1e-4)), threads=None,
                     val_every=500, ckpt_every=100, keep_checkpoints=20, stage2_steps=100000)
yaml.safe_dump(base, open(w / "cfg.yaml", "w"), sort_keys=False)
EOF
cp "$W/cfg.yaml" "$OUT/cfg.yaml"

# 3. each run: a probe to step PROBE (the pace between checkpoints 100 and PROBE, measured with every run going),
# then --resume with the fitted schedule; the deadline stops whatever is still going
fit() {  # NAME CFG DEST
  local N=$1 CFG=$2 D=$3 P= NSTEPS=0 SLOW= PACE
  local TR="$PY -m kpcn.train -c $CFG --name $N --results-dir $W/r --no-progress" CK=$W/r/$N/checkpoints
  mkdir -p "$D"
  rm -rf "$W/r/$N"  # a previous call's run on a machine still warm: its checkpoints would end the probe at once
  $TR --overwrite >"$D/train1.log" 2>&1 &
  P=$!
  while [ ! -f "$CK/step_$PROBE.pt" ]; do
    kill -0 $P 2>/dev/null || { echo "$N: probe run ended early"; tail -20 "$D/train1.log"; return 6; }
    [ $(( $(date +%s) - T0 )) -ge $((BUDGET - 60)) ] && { echo "$N: probe too slow: stopping"; SLOW=1; break; }
    sleep 0.5
  done
  sleep 0.5
  kill $P; wait $P 2>/dev/null
  if [ -z "$SLOW" ]; then
    read -r PACE NSTEPS < <($PY -c "
import os, time; t100, t2 = (os.path.getmtime('$CK/step_%d.pt' % s) for s in (100, $PROBE))
pace = (t2 - t100) / ($PROBE - 100)
print(pace, int($PROBE + max(0, $T0 + $BUDGET - time.time() - 40) / pace))")
    echo "$N: probe step $PROBE at $(el) s, $PACE s/step, $NSTEPS steps in all"
  fi
  P=
  [ "$NSTEPS" -gt 0 ] && { $TR --resume --set train.stage2_steps=$NSTEPS >"$D/train2.log" 2>&1 & P=$!; }
  while [ -n "$P" ] && kill -0 $P 2>/dev/null; do
    [ $(( $(date +%s) - T0 )) -ge $((BUDGET - 12)) ] && { echo "$N: deadline: stopping the run"; kill $P; break; }
    sleep 1
  done
  [ -n "$P" ] && wait $P 2>/dev/null
  echo "$N: training ended at $(el) s"
  if [ -f "$W/r/$N/model.safetensors" ]; then
    cp "$W/r/$N/model.safetensors" "$D/model.safetensors"
  elif [ -f "$CK/latest.pt" ]; then  # the last checkpoint's weights
    $PY -c "
from kpcn.checkpoint import load_model_file, save_weights
save_weights('$D/model_partial.safetensors', load_model_file('$CK/latest.pt'))"
  fi
  cp "$W/r/$N/metrics.jsonl" "$D/" 2>/dev/null
  tail -3 "$D/train2.log" 2>/dev/null
}
for e in ${EXTRA:-}; do
  n=${e%%=*}; c=${e#*=}
  $PY - "$W" "$n" "$c" <<'EOF' || exit 5
import os, sys, yaml
from pathlib import Path
w, name, src = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
main, cfg = yaml.safe_load(open(w / "cfg.yaml")), yaml.safe_load(open(src))
data = dict(main["data"], patch_size=cfg.get("data", {}).get("patch_size", main["data"]["patch_size"]), workers=3)
train = dict(cfg.get("train", {}))
lr = float(os.environ.get("EXTRA_LR", 2e-4))
train.update(stage1_steps=0, stage2_steps=100000, lr=lr, stage2_lr=lr, schedule="onecycle", threads=None,
             val_every=500, ckpt_every=100, keep_checkpoints=20)
if os.environ.get("EXTRA_BATCH"):
    train["batch_size"] = int(os.environ["EXTRA_BATCH"])
train.setdefault("batch_size", main["train"]["batch_size"])
train.setdefault("grad_clip", 1.0)
out = {"name": name, "model": cfg["model"], "data": data, "train": train}
yaml.safe_dump(out, open(w / f"cfg_{name}.yaml", "w"), sort_keys=False)
print(name, "from", src, "patch", data["patch_size"], "batch", train["batch_size"], flush=True)
EOF
  mkdir -p "$OUT/$n"; cp "$W/cfg_$n.yaml" "$OUT/$n/cfg.yaml"
  fit "$n" "$W/cfg_$n.yaml" "$OUT/$n" > "$OUT/$n/fit.log" 2>&1 &
done
fit g "$W/cfg.yaml" "$OUT"
wait
for e in ${EXTRA:-}; do cat "$OUT/${e%%=*}/fit.log"; done
ls "$W/d" | grep -c '^s' >"$OUT/scenes.txt"

# 5. what comes back from the device is at most 8 files of 16 MiB, 64 MiB in all (a paper-width U-Net's weights are
# 63 MB): the main run's weights stay as they are, the extra runs' are stored as float16 (they load into float32
# models as they are), and everything else goes into one tar in 15 MiB parts. Here: cat pack.tar.* | tar x
if [ -n "${EXTRA:-}" ]; then
  $PY - "$OUT" ${EXTRA} <<'EOF'
import sys
from pathlib import Path
from safetensors import safe_open
from safetensors.torch import save_file
for e in sys.argv[2:]:
    for f in (Path(sys.argv[1]) / e.split("=")[0]).glob("model*.safetensors"):
        with safe_open(str(f), framework="pt") as h:
            meta, state = h.metadata(), {k: h.get_tensor(k) for k in h.keys()}
        save_file({k: v.half() if v.is_floating_point() else v for k, v in state.items()}, str(f), metadata=meta)
EOF
  rm -f "$W"/pack.tar.*
  (cd "$OUT" && tar cf - --exclude='./model*.safetensors' .) | split -b 15M - "$W/pack.tar." \
    && (cd "$OUT" && find . -mindepth 1 -maxdepth 1 -not -name 'model*.safetensors' -exec rm -rf {} +) \
    && mv "$W"/pack.tar.* "$OUT"/
  ls -la "$OUT"
fi
echo "all done at $(el) s"
