#!/usr/bin/env bash
# The geometry model (docs/geometry.md): WorldPack with the recipe, fine-tuned
# with the best-overlap observed frames warped into the target view as an
# input, then measured where the rollout issue measures (the 48-trajectory
# test suite), in the one-step probe (inside and outside the warp's
# validity mask, against the fused and composite references) and on the
# REST walk. Resumable: each stage continues or reuses what is done.
#   ./scripts/recipe.sh prepare            # first: data/train120, data/val, data/loopnav-test, runs/base
#   ./scripts/geometry.sh train            # STEPS (8000 in all, from the recipe's 2,337), MINUTES
#   ./scripts/geometry.sh export           # -> fixtures/variants/worldpack_geometry
#   ./scripts/geometry.sh eval | probe | walk
# POLICY=nearest_frame_packing (or memory_retrieval) RUN=runs/geo_nfp OUT=... trains
# and exports the same fine-tune from another recipe model (the issue-19 ablation,
# rolled out as trained and with --plan-warps: warps only from its own plan's frames).
set -euo pipefail
cd "$(dirname "$0")/.."
run="${RUN:-runs/geo}"
out="${OUT:-fixtures/variants/worldpack_geometry}"
steps="${STEPS:-8000}"
threads="${THREADS:-1}"
bin=target/release/worldpack
geo="worldpack_geometry=$out"
policy="${POLICY:-worldpack}"
recipe=fixtures/variants/worldpack_recipe
init_model=fixtures/variants/${policy}_recipe   # the recipe model this fine-tune starts from
init_run=runs/${policy}_recipe
[ "$policy" = worldpack ] && init_run=runs/wp_recipe

# A models folder whose `baseline` is the first-trained one (fixtures/variants/baseline_12k).
first_baseline() {
  mkdir -p runs/geo/first-baseline
  [ -e runs/geo/first-baseline/baseline ] || ln -s "$PWD/fixtures/variants/baseline_12k" runs/geo/first-baseline/baseline
}

case "${1:-}" in
  train)
    mkdir -p "$run"
    [ -f "$init_run/cdit-$policy.pt" ] || ./scripts/model.sh recover --model "$init_model" --run "$init_run"
    [ -e "$run/latents" ] || ln -s "$PWD/runs/base/latents" "$run/latents"
    [ -e "$run/autoencoder.pt" ] || ln -s "$PWD/runs/base/autoencoder.pt" "$run/autoencoder.pt"
    [ -f "$run/config.json" ] || cp "$init_run/config.json" "$run/config.json"
    ./scripts/model.sh train --data data/train120 --run "$run" --policy "$policy" --steps "$steps" ${MINUTES:+--minutes "$MINUTES"} \
        --init-from "$init_run/cdit-$policy.pt" --threads "$threads" --memory-focus 0.5 \
        --context-noise 0.7 --generated-level 0.3 --warp ;;
  export)
    ./scripts/model.sh export --run "$run" --policy "$policy" --layouts "$policy" --data data/val --out "$out" --half --threads "$threads" ;;
  eval)
    # Their baseline row is the first-trained baseline these fine-tunes started from. The
    # ablation rows run when their models are there; they are not shipped: make them with
    # `./scripts/recipe.sh train POLICY` (the *_recipe models, baseline_ctx_noise with
    # RECIPE as in recipe.sh) and `POLICY=... RUN=... OUT=fixtures/variants/POLICY_geometry
    # ./scripts/geometry.sh train && ... export` (the *_geometry ones).
    first_baseline
    extra=(--extra worldpack_recipe=$recipe --extra "$geo" --plan-warps worldpack_geometry)
    for name in baseline_ctx_noise baseline_continued nearest_frame_packing_recipe memory_retrieval_recipe \
                nearest_frame_packing_geometry memory_retrieval_geometry; do
      [ -f "fixtures/variants/$name/manifest.json" ] || continue
      extra+=(--extra "$name=fixtures/variants/$name")
      [[ "$name" == *_geometry ]] && extra+=(--plan-warps "$name")
    done
    "$bin" eval --suite data/loopnav-test --models runs/geo/first-baseline --policies baseline --out runs/recipe/eval-test \
        "${extra[@]}" --composite baseline --composite worldpack_geometry --against worldpack_recipe \
        --strip worldpack_geometry,worldpack_recipe,baseline,reproject_fused --threads "${EVAL_THREADS:-2}" "${@:2}" ;;
  probe)
    # Only the rows the geometry questions need: the baseline (required), WorldPack with the recipe, the geometry model.
    first_baseline
    "$bin" probe --suite "${SUITE:-data/loopnav-test}" --models runs/geo/first-baseline --stride "${STRIDE:-12}" \
        --extra worldpack_recipe=$recipe --extra "$geo" --composite worldpack_geometry \
        --contrast "worldpack_geometry:reproject 3 best frames, fused" \
        --contrast "worldpack_geometry:fused warp, baseline in its holes" \
        --contrast "worldpack_geometry, warp overlaid:fused warp, baseline in its holes" \
        --contrast "worldpack_geometry:worldpack_recipe" --threads "${EVAL_THREADS:-2}" --out runs/geo/probe.json "${@:2}" ;;
  walk)
    .venv/bin/python scripts/rest_walk.py --out docs/geometry/rest_walk --observe-outbound \
        --row worldpack_geometry="$out":worldpack --row worldpack_recipe=$recipe:worldpack \
        --row baseline=fixtures/variants/baseline_12k:baseline ;;
  *) echo "usage: $0 train | export | eval | probe | walk" >&2; exit 2 ;;
esac
