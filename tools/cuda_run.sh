#!/usr/bin/env bash
# The CUDA run recorded in docs/cuda_run.md: on a machine with a CUDA GPU, from the repository root,
#
#     OUT=cuda_run tools/cuda_run.sh [WHEELS_DIR]
#
# (PARTS="tests" or PARTS="bench" runs one half: the render and the tests, or the parity sweep and the
# rasterizer benchmark; both by default.)
# installs the wheels in WHEELS_DIR (gsplat and any other package the machine lacks; offline),
# renders one demo view with the CLI (the default backend, triton: its first-use JIT compilation
# happens here), runs the Triton backend's tests compiled on the GPU and the tests marked `cuda`,
# then the parity sweep (bench/gsplat_parity.py) with its speed rows and the rasterizer benchmark
# (bench/raster.py: peak memory, where the time goes, first use in a fresh process), and prints a
# short summary. Everything lands under $OUT.
set -u
OUT=$(realpath -m "${OUT:-cuda_run}")
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=4
if [ -n "${1:-}" ]; then
    python3 -m pip install -q --no-index --no-deps --no-cache-dir --break-system-packages "$1"/*.whl || exit 1
fi
python3 - > "$OUT/machine.txt" <<'EOF' || exit 1  # without a GPU every part below would pass on the CPU, or skip
import platform, sys, torch
if not torch.cuda.is_available():
    sys.exit(f"tools/cuda_run.sh: no CUDA GPU visible to torch {torch.__version__}: run it on a CUDA machine")
import triton, gsplat  # gsplat: the parity sweep's reference (WHEELS_DIR, when the machine lacks it)
print(f"GPU: {torch.cuda.get_device_name(0)}; torch {torch.__version__}, CUDA {torch.version.cuda}; "
      f"triton {triton.__version__}; gsplat {gsplat.__version__}; Python {platform.python_version()}")
EOF
cat "$OUT/machine.txt"

PARTS=${PARTS:-tests bench}
if [[ " $PARTS " == *" tests "* ]]; then
start=$(date +%s)
timeout 300 python3 -m artnvg_core render artnvg_core/demo/bear.ply --cameras artnvg_core/demo/transforms.json \
    --out "$OUT/renders" --views 0 --scale 0.5 --device cuda > "$OUT/first_render.txt" 2>&1
echo "first render (Triton's JIT compilation included): exit $?, $(( $(date +%s) - start )) s" | tee -a "$OUT/first_render.txt"
grep -E "gsplat|triton|rendering|\[1/1\]" "$OUT/first_render.txt"

timeout 240 python3 -m pytest -p no:cacheprovider -rA tests/test_raster_triton.py > "$OUT/triton_tests.txt" 2>&1
echo "triton tests (compiled on the GPU): exit $?"
grep -E "passed|failed" "$OUT/triton_tests.txt" | tail -3

timeout 240 python3 -m pytest -m cuda -p no:cacheprovider -rA --junitxml="$OUT/cuda_tests.xml" tests \
    > "$OUT/cuda_tests.txt" 2>&1
echo "cuda tests: exit $?"
grep -E "^(PASSED|FAILED|ERROR|SKIPPED)|passed|failed" "$OUT/cuda_tests.txt" | tail -40

fi

if [[ " $PARTS " == *" bench "* ]]; then
(cd bench && timeout 300 python3 gsplat_parity.py --out "$OUT" --speed 100000,1000000) > "$OUT/parity.txt" 2>&1
echo "parity sweep: exit $?"
sed -n '/^### /,$p' "$OUT/parity.txt"

(cd bench && timeout 240 python3 raster.py --sizes 1024 --counts 100000,1000000 --stages 1000000 --first-use) \
    > "$OUT/raster.txt" 2>&1
echo "rasterizer benchmark: exit $?"
sed -n '/^### /,$p' "$OUT/raster.txt"
fi
