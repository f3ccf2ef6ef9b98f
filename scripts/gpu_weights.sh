#!/usr/bin/env bash
# Before a GPU lease, whose tree (tracked files and the carried .gpu) must stay under 64 MiB, move every shipped
# weights file but the one the run starts from out of the tree; after it, move them back:
#   bash scripts/gpu_weights.sh hold [KEEP]     # KEEP: a file name in src/kpcn/weights (default unet_wide64n.safetensors, the default's)
#   bash scripts/gpu_weights.sh restore
# HOLD (default /tmp/kpcn_weights_hold) is where they wait; restore refuses to overwrite a file in the tree.
set -eu
HOLD=${HOLD:-/tmp/kpcn_weights_hold}
DIR=$(cd "$(dirname "$0")/.." && pwd)/src/kpcn/weights
case "${1:-}" in
  hold)
    KEEP=${2:-unet_wide64n.safetensors}
    [ -f "$DIR/$KEEP" ] || { echo "gpu_weights: no $DIR/$KEEP" >&2; exit 2; }
    mkdir -p "$HOLD"
    for f in "$DIR"/*.safetensors; do
      [ "$(basename "$f")" = "$KEEP" ] || mv -n "$f" "$HOLD"/
    done
    echo "kept $KEEP; weights in the tree: $(du -sh "$DIR" | cut -f1); held in $HOLD: $(ls "$HOLD" | wc -l) files" ;;
  restore)
    for f in "$HOLD"/*.safetensors; do
      [ -e "$f" ] || continue
      [ -e "$DIR/$(basename "$f")" ] && { echo "gpu_weights: $DIR/$(basename "$f") exists; left in $HOLD" >&2; exit 3; }
      mv "$f" "$DIR"/
    done
    echo "weights in the tree: $(ls "$DIR"/*.safetensors | wc -l) files, $(du -sh "$DIR" | cut -f1)" ;;
  *)
    echo "usage: $0 hold [KEEP] | restore" >&2; exit 2 ;;
esac
