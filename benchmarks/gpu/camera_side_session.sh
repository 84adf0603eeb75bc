#!/usr/bin/env bash
# Issue 52's device work on a lent H100/H200 in one call of the device tool: the steps'
# time limits add up to 550 s (docs/gpu.md, "Issue 52 on a lent GPU": the wheels to carry,
# the call, what comes back). Each step writes as it goes, so that a call stopped early
# still returns what the earlier steps measured:
#   1. every kernel of every task compiled cold, in parallel (item 2 on a GPU machine);
#   2. Nsight Compute of sample matching (line information: stalls by Python line) and of
#      the render it is compared with (item 3: occupancy, divergence, atomics, memory);
#   3. paths/s of the render and the camera-side kernels by block size, then sample
#      matching under register caps (python -m benchmarks gpu.camera_side).
# Everything lands in $OUT/issue52.tgz (the tables, logs and ncu's CSV pages) and
# $OUT/ncu_reports.tgz (the ncu reports), within the tool's 8 files.
set -u
work=/tmp/issue52
mkdir -p "$work"
log="$work/session.log"
step() {  # step NAME SECONDS COMMAND...: run with a time limit, log its time and status
    local name=$1 limit=$2 start=$SECONDS
    shift 2
    timeout "$limit" "$@" >"$work/$name.log" 2>&1
    echo "$name: status $? in $((SECONDS - start)) s" | tee -a "$log"
}
pack() {
    tar czf "$OUT/issue52.tgz" -C "$work" --exclude='*.ncu-rep' . 2>/dev/null
    tar czf "$OUT/ncu_reports.tgz" -C "$work" --wildcards '*.ncu-rep' 2>/dev/null
}
trap pack EXIT

python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD CLOUDCT_CACHE_DIR=/tmp/cloudct-cache PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,clocks.max.sm,memory.total --format=csv \
    >"$work/gpu.csv"
cloudct=(python3 -c "import sys; from cloudct.cli import main; sys.exit(main(sys.argv[1:]))")

step warm 180 "${cloudct[@]}" cache --warm --backend cuda --jobs 16

ncu_of() {  # ncu_of KERNEL [--lineinfo]: the second launch of one kernel, every section
    local name=$1
    shift
    ncu --clock-control none --set full --import-source yes -f -o "$work/ncu_$name" \
        -k "regex:$(kernel_name "$name")" --launch-skip 1 --launch-count 1 \
        python3 -m benchmarks gpu.camera_side --ncu-target --kernels "$name" "$@" &&
        ncu --import "$work/ncu_$name.ncu-rep" --csv --page details >"$work/ncu_${name}_details.csv" &&
        ncu --import "$work/ncu_$name.ncu-rep" --csv --page raw >"$work/ncu_${name}_raw.csv"
}
kernel_name() {
    python3 -c "from benchmarks.gpu.camera_side import KERNELS; print(KERNELS['$1'])"
}
export -f ncu_of kernel_name
export work
step ncu_sm 130 bash -c 'ncu_of sm --lineinfo'
step ncu_render 50 bash -c 'ncu_of render'

step occupancy 90 python3 -m benchmarks gpu.camera_side --max-registers 0 \
    --output "$work/camera_side"
step register_caps 100 python3 -m benchmarks gpu.camera_side --kernels sm \
    --max-registers 168 128 --threads-per-block 128 --output "$work/camera_side_caps"
