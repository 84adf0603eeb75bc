#!/bin/bash
# Device script, 2026-11-27 (session 7): the estimator matrix's [cuda] case (DRT under the
# power law on hardware) beside a GPU retrieval of Mie and HG measurements of the single cloud
# with the score function, the same settings and wall time (issue 38).
T0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 CLOUDCT_CACHE_DIR=/tmp/cloudct-cache
cloudct() { python3 -c 'import sys; from cloudct.cli import main; sys.exit(main(sys.argv[1:]))' "$@"; }
nvidia-smi --query-gpu=name,driver_version --format=csv > $OUT/gpu.txt
(python3 -m pytest -v -p no:cacheprovider --durations=5 "tests/test_estimator_matrix.py::test_the_matrix_on_each_back_end[cuda]" > $OUT/matrix.log 2>&1; echo "matrix done at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt) &
MATRIX=$!
echo "installed at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
# warm-up: compile the render and score kernels once for each optics (not timed)
for o in mie hg; do
  cloudct retrieve gpu_run/${o}_measurements.nc --init gpu_run/init_${o}.nc --estimator score \
    --iterations 2 --photons 20000 --backend cuda -o /tmp/warm_${o}.nc --overwrite > $OUT/warm_${o}.log 2>&1
  echo "warm $o at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
done
LEFT=$(( 540 - ($(date +%s) - T0) )); TL=$(( (LEFT - 40) / 2 )); [ $TL -gt 170 ] && TL=170
echo "time limit $TL s" >> $OUT/times.txt
for o in mie hg; do
  truth=gpu_run/mie_truth.nc; [ $o = hg ] && truth=gpu_run/hg_truth.nc
  cloudct retrieve gpu_run/${o}_measurements.nc --init gpu_run/init_${o}.nc --estimator score \
    --truth $truth --time-limit $TL --iterations 100000 --backend cuda \
    -o $OUT/gpu_${o}_score.nc --overwrite > $OUT/retrieve_${o}.log 2>&1
  echo "retrieve $o at $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
done
rm -f $OUT/*.checkpoint.nc
wait $MATRIX
