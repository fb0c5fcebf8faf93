#!/usr/bin/env bash
# Run gpuslice on a lent NVIDIA GPU machine (the device tool's nvidia-h200): OpenCL set up, tests, GPU-vs-PoCL
# comparison and benchmarks. docs/GPU.md says how to prepare the carried folders and how to call it.
#
#   bash scripts/gpu_check.sh [STAGES]      STAGES: comma-separated, default setup,devices,compare,tests
#
# Stages (each writes its log to $OUT, default /tmp/gpu-out):
#   setup    install the carried wheels (.whl/*.whl, .whl/pocl.tar.xz: pyopencl's PoCL) into /tmp/site; unpack the
#            carried meshes (.meshes/meshes.tar.xz) to ../shared/meshes; find NVIDIA's libnvidia-opencl and write
#            /tmp/icd/{nvidia,pocl}.icd for OCL_ICD_VENDORS; the GL libraries (.gl/*.deb) when carried
#   devices  nvidia-smi, CPU, `gpuslice devices`
#   tests    the whole pytest suite with GPUSLICE_DEVICE=nvidia (pytest-xdist, 12 workers)
#   compare  scripts/gpu_compare.py --a nvidia --b pocl: weld, contours and runs on every shared mesh
#   forked   tests/test_threads.py on the GPU (a forked child is told its parent's context does not work)
#   stages   scripts/gpu_stages.py: in-process stages on each device, the contour meshes and 1.6 M facets
#   probe    OpenCL start-up per platform, the GL rasteriser's renderer and a small GL job against the runs,
#            whole-process `gpuslice slice` on each device
#   profile  scripts/profile_stages.py: the armadillo job to a 12K GOO, function by function, on each device
#   abgpu    tests/raster on the GPU, then this tree against a copy of the code before in .old/ (carried), the
#            armadillo job to GOO in process (scripts/profile_stages.py's timed run), alternated
#   large    scripts/make_large.py, then the big-mesh benchmark (whole process) on each device
#   resin    scripts/bench_runs.py and scripts/bench_resin.py (armadillo job, 12K and 16K, GOO) on each device,
#            and the GL rasteriser (--raster-backend gl) against the runs on the GPU
# Every stage sources the environment setup writes (/tmp/gpu-env.sh). Begin every call with setup (~5 s): each call
# sends the working tree afresh, without the gpuslice/kernels link that setup makes.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/gpu-out}
mkdir -p "$OUT"
STAGES=",${1:-setup,devices,compare,tests},"
has() { [[ $STAGES == *",$1,"* ]]; }
stamp() { echo "== $(date +%T) $*"; }

if has setup; then
  stamp setup
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
  [ -f .whl/pocl.tar.xz ] && tar xJf .whl/pocl.tar.xz -C /tmp/site
  if [ -f .meshes/meshes.tar.xz ] && [ ! -d ../shared/meshes ]; then
    mkdir -p ../shared && tar xJf .meshes/meshes.tar.xz -C ../shared
  fi
  ln -sfn ../kernels gpuslice/kernels  # the package's kernels, as the editable install maps them
  lib=$(find /usr/local/nvidia /usr/lib /usr/lib64 /lib /lib64 -name 'libnvidia-opencl.so*' 2>/dev/null | sort | head -1)
  mkdir -p /tmp/icd
  [ -n "$lib" ] && echo "$lib" > /tmp/icd/nvidia.icd
  pocl=$(ls /tmp/site/pyopencl/.libs/libpocl-*.so 2>/dev/null | head -1)
  [ -n "$pocl" ] && echo "$pocl" > /tmp/icd/pocl.icd
  echo "libnvidia-opencl: ${lib:-NOT FOUND}; pocl: ${pocl:-none}"
  if ls .gl/*.deb >/dev/null 2>&1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
  fi
  mkdir -p /tmp/bin
  printf '#!/bin/sh\nexec python3 -m gpuslice.cli "$@"\n' > /tmp/bin/gpuslice && chmod +x /tmp/bin/gpuslice
  # (the console script beside the interpreter, as an install makes it: some tests run it)
  cp /tmp/bin/gpuslice "$(dirname "$(command -v python3)")/gpuslice" 2>/dev/null || true
  cat > /tmp/gpu-env.sh <<EOF
export PYTHONPATH=$PWD:/tmp/site OCL_ICD_VENDORS=/tmp/icd PYTHONUNBUFFERED=1 PATH=/tmp/bin:\$PATH
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
EOF
fi
# shellcheck disable=SC1091
. /tmp/gpu-env.sh

if has devices; then
  stamp devices
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv
  lscpu | grep -E '^(Model name|CPU\(s\))'
  python3 -c "import numpy, pyopencl; print('numpy', numpy.__version__, 'pyopencl', pyopencl.VERSION_TEXT)"
  python3 -m gpuslice.cli devices 2>&1 | tee "$OUT/devices.txt"
fi

if has compare; then
  stamp compare
  timeout 200 python3 scripts/gpu_compare.py --a nvidia --b pocl --json "$OUT/compare.json" > "$OUT/compare.log" 2>&1
  echo "compare exit $?"
  grep -v ' same$' "$OUT/compare.log" | cut -c1-300 | tail -40
fi

if has tests; then
  stamp tests
  GPUSLICE_DEVICE=nvidia timeout 330 python3 -m pytest -q -n 12 -p no:cacheprovider --timeout 300 \
    -o addopts="" -rfEs tests > "$OUT/tests.log" 2>&1
  echo "pytest exit $?"
  grep -E '^(FAILED|ERROR)' "$OUT/tests.log" | cut -c1-200 | head -60
  grep -E '^SKIPPED' "$OUT/tests.log" | sed -E 's/^SKIPPED \[[0-9]+\] //' | cut -c1-160 | sort | uniq -c | sort -rn | head -40
  tail -3 "$OUT/tests.log"
fi

if has forked; then
  stamp forked
  GPUSLICE_DEVICE=nvidia timeout 120 python3 -m pytest -q -p no:cacheprovider -o addopts="" tests/test_threads.py 2>&1 \
    | tail -3
fi

if has stages; then
  stamp make_large
  timeout 100 python3 scripts/make_large.py --only nefertiti_loop2 > /tmp/make_large.log 2>&1
  stamp stages
  timeout 240 python3 scripts/gpu_stages.py --devices nvidia,pocl --large /tmp/gpuslice-large --profile \
    --json "$OUT/stages.json" > "$OUT/stages.log" 2>&1
  echo "exit $?"; grep -E '^\|' "$OUT/stages.log"
fi

if has probe; then
  stamp "probe: OpenCL start-up"
  python3 - <<'PYEOF'
import time
t0 = time.perf_counter()
import pyopencl as cl
t1 = time.perf_counter()
ps = cl.get_platforms()
t2 = time.perf_counter()
print(f"import pyopencl {1e3 * (t1 - t0):.0f} ms, get_platforms {1e3 * (t2 - t1):.0f} ms")
for p in ps:
    d = p.get_devices()[0]
    t3 = time.perf_counter()
    ctx = cl.Context([d])
    cl.CommandQueue(ctx)
    print(f"{p.name}: context + queue {1e3 * (time.perf_counter() - t3):.0f} ms")
PYEOF
  stamp "probe: GL"
  timeout 60 python3 -c "import moderngl; c = moderngl.create_standalone_context(backend='egl'); print(c.info['GL_RENDERER'], '|', c.info['GL_VERSION'])" 2>&1 | tail -2
  b60=../shared/meshes/benchy.stl
  TIMEFORMAT="%R s"
  for b in gl auto gl auto; do
    echo -n "benchy 60 mm 3840x2400 goo --raster-backend $b: "
    { time SOURCE_DATE_EPOCH=1700000000 GPUSLICE_DEVICE=nvidia timeout 60 python3 -m gpuslice.cli raster $b60 --fit 60 -t 0.05 \
        --resolution 3840x2400 --pixel 0.05 --gamma 0 --raster-backend $b -o /tmp/b_$b.goo > /tmp/b_$b.log 2>&1 ; } 2>&1
    tail -1 /tmp/b_$b.log | cut -c1-200
  done
  cmp /tmp/b_gl.goo /tmp/b_auto.goo && echo "gl and runs GOO identical"
  python3 - <<'PYEOF'
import sys
import numpy as np
sys.path.insert(0, "tests/raster")
from goo_reader import layer_mask, read_goo
a, b = read_goo("/tmp/b_gl.goo"), read_goo("/tmp/b_auto.goo")
same, ious, grey = 0, [], []
for i in range(0, len(a.layers), 4):
    ma, mb = layer_mask(a, i), layer_mask(b, i)
    same += bool(np.array_equal(ma, mb))
    u = np.count_nonzero((ma >= 128) | (mb >= 128))
    if u:
        ious.append(np.count_nonzero((ma >= 128) & (mb >= 128)) / u)
print(f"gl vs runs masks (gamma 0): {same} of {len(range(0, len(a.layers), 4))} layers checked (every 4th) identical; IoU min {min(ious):.5f}, "
      f"median {np.median(ious):.5f}")
PYEOF
  stamp "probe: whole-process slice"
  for i in 1 2 3; do
    for d in nvidia pocl; do
      echo -n "slice benchy $d: "
      { time GPUSLICE_DEVICE=$d python3 -m gpuslice.cli slice $b60 --fit 60 -t 0.05 -o /tmp/s_$d.npz > /tmp/s.log 2>&1 ; } 2>&1
      grep -i "times" /tmp/s.log | cut -c1-220
    done
  done
  cmp /tmp/s_nvidia.npz /tmp/s_pocl.npz && echo "npz identical"
fi

if has profile; then
  stamp "profile: the armadillo job to GOO, function by function (scripts/profile_stages.py)"
  mkdir -p /tmp/gpuslice-bench
  job=$(python3 -c "import sys; sys.path.insert(0, 'scripts'); import bench_resin; from pathlib import Path; \
print(bench_resin.job_stl('armadillo', Path('/tmp/gpuslice-bench')))")
  for d in nvidia pocl; do
    for g in 0 1; do
      GPUSLICE_DEVICE=$d timeout 120 python3 scripts/profile_stages.py --top 30 -- raster "$job" --fit 95 -t 0.05 \
        --resolution 11520x5120 --pixel 0.019 --gamma $g -o /tmp/prof.goo 2>&1 | grep -v warning > "$OUT/prof_${d}_$g.txt"
      echo "## $d gamma $g"; grep -E '^(warm-up|timed)' "$OUT/prof_${d}_$g.txt"
    done
  done
fi

if has abgpu; then
  stamp "raster tests on the GPU"
  GPUSLICE_DEVICE=nvidia timeout 150 python3 -m pytest -q -n 12 -p no:cacheprovider --timeout 140 -o addopts="" \
    tests/raster > "$OUT/raster_tests.log" 2>&1
  echo "pytest exit $?"; tail -2 "$OUT/raster_tests.log"
  stamp "A/B: this tree against .old/ (a copy of the code before), the armadillo job to GOO in process"
  mkdir -p /tmp/gpuslice-bench
  job=$(python3 -c "import sys; sys.path.insert(0, 'scripts'); import bench_resin; from pathlib import Path; \
print(bench_resin.job_stl('armadillo', Path('/tmp/gpuslice-bench')))")
  for rep in 1 2; do
    for side in new old; do
      pp=$PWD; [ $side = old ] && pp=$PWD/.old
      for g in 0 1; do
        echo -n "$side gamma $g: "
        PYTHONPATH=$pp:/tmp/site GPUSLICE_DEVICE=nvidia timeout 60 python3 scripts/profile_stages.py --top 0 -- raster \
          "$job" --fit 95 -t 0.05 --resolution 11520x5120 --pixel 0.019 --gamma $g -o /tmp/ab.goo 2>&1 | grep '^timed'
      done
    done
  done
fi

if has large; then
  stamp make_large
  timeout 200 python3 scripts/make_large.py --only nefertiti_loop2,nefertiti_loop3 > "$OUT/make_large.log" 2>&1
  tail -2 "$OUT/make_large.log"
  for d in nvidia pocl; do
    stamp "large $d"
    GPUSLICE_DEVICE=$d timeout 240 python3 scripts/bench_contours.py --large \
      --large-meshes nefertiti_loop2,nefertiti_loop3 --large-thickness 0.02,0.05 \
      --json "$OUT/large_$d.json" > "$OUT/large_$d.log" 2>&1
    echo "exit $?"; grep -E '^\|' "$OUT/large_$d.log" | head -20
  done
fi

if has resin; then
  for d in nvidia pocl; do
    stamp "runs $d"
    GPUSLICE_DEVICE=$d timeout 150 python3 scripts/bench_runs.py --skip-old --skip-numpy --repeat 3 \
      > "$OUT/runs_$d.log" 2>&1
    echo "exit $?"; tail -25 "$OUT/runs_$d.log"
    stamp "resin $d"
    GPUSLICE_DEVICE=$d timeout 200 python3 scripts/bench_resin.py --jobs armadillo --formats goo --gammas 0,1 \
      --no-z4 --repeat 3 --json "/tmp/resin_$d.json" > "$OUT/resin_$d.log" 2>&1
    echo "exit $?"; tail -15 "$OUT/resin_$d.log"
  done
  stamp "gl against runs on the GPU"
  job=$(ls /tmp/gpuslice-bench/armadillo*upright*.stl 2>/dev/null | head -1)
  if [ -n "$job" ]; then
    TIMEFORMAT="%R s"
    for b in gl auto; do
      echo -n "raster --raster-backend $b: "
      { time GPUSLICE_DEVICE=nvidia timeout 90 python3 -m gpuslice.cli raster "$job" --fit 95 -t 0.05 \
          --resolution 11520x5120 --pixel 0.019 --gamma 0 --raster-backend $b -o /tmp/gl_$b.goo >/dev/null ; } 2>&1
    done
    cmp /tmp/gl_gl.goo /tmp/gl_auto.goo && echo "gl and runs GOO identical"
  fi
fi
stamp done
