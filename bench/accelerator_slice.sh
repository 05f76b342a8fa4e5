#!/bin/bash
# The 1/10 slice (bench/full_map_slice.py) on a GPU machine, as one prepared run: the engine's
# accelerator defaults (lane pools as wide as the chunk's slice of the device, 2^18-cell chunks)
# apply by themselves there. The machine's image has JAX, diffrax, equinox, xarray and scipy but
# not zarr: its wheels travel in .whl (python 3.12, manylinux), fetched here with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#     --implementation cp --platform manylinux_2_17_x86_64 -d .whl \
#     zarr==3.1.6 numcodecs==0.16.6 donfig==0.8.1.post1 google-crc32c
# Run from the repository root:
#   OUT=<folder> [BUDGET=s] [PROTOCOLS=paper] bash bench/accelerator_slice.sh
# (BUDGET: seconds the slice may take before it is stopped; its log goes to $OUT/slice.txt.)
export PYTHONUNBUFFERED=1 JAXDEA_COMPILE_CACHE=off
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD/src
T0=$(date +%s)
{ nvidia-smi --query-gpu=name,memory.total,clocks.max.sm --format=csv; nproc
  python3 -c "
import jax, diffrax, equinox, numpy, scipy, xarray, zarr, jaxdea
from jaxdea.engine.sharding import on_accelerator
from jaxdea.engine.batch import default_lanes
print('jax', jax.__version__, jax.devices(), 'diffrax', diffrax.__version__, 'equinox',
      equinox.__version__, 'numpy', numpy.__version__, 'xarray', xarray.__version__,
      'zarr', zarr.__version__, 'x64', jax.config.jax_enable_x64)
print('on_accelerator', on_accelerator(), 'lanes for 5000 cells', default_lanes(5000))"
} 2>&1 | tee $OUT/env.txt
left=$(( ${BUDGET:-540} - ($(date +%s) - T0) ))
echo "== slice (limit ${left}s)"
timeout $left python3 bench/full_map_slice.py --protocols ${PROTOCOLS:-neighbour,paper} \
  --samples 8 $SLICE_ARGS 2>&1 | tee $OUT/slice.txt | grep -v "it/s\]"
echo "rc=${PIPESTATUS[0]} after $(( $(date +%s) - T0 ))s"
