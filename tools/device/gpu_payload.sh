#!/bin/bash
# Builds .dev/ (git-ignored): what tools/device/gpu_check.sh needs on a lent GPU machine that has
# python3 3.12 with torch, numpy, scipy, opencv and pytest but no internet and no open3d, pydantic
# or X11/GL libraries. About 52 MB, under the device tool's 64 MiB. The wheels are unpacked as
# shipped; Open3D's viewers, which need packages the machine lacks, are left out at import time by
# tools/device/headless/sitecustomize.py, not by editing the wheel.
# Run here (with internet), then: device run `bash tools/device/gpu_check.sh`, carry [".dev"].
set -euo pipefail
cd "$(dirname "$0")/../.."
rm -rf .dev && mkdir -p .dev/site .dev/debs /tmp/pmvir-whl
py=(--no-deps --only-binary=:all: --python-version 3.12 --implementation cp
    --platform manylinux_2_31_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64
    --platform manylinux2014_x86_64 -d /tmp/pmvir-whl)
python3 -m pip download "${py[@]}" open3d-cpu==0.19.0 pydantic==2.14.4 pydantic_core==2.50.5 \
    typing-inspection==0.4.5 annotated-types typing_extensions==4.16.0 plyfile==1.1.5
for w in /tmp/pmvir-whl/*.whl; do unzip -q -o "$w" -d .dev/site; done
# The viewers' assets and the torch ops, unused, are left out to fit the 64 MiB.
rm -rf .dev/site/open3d/resources .dev/site/open3d/cpu/open3d_torch_ops.so
so=.dev/site/open3d/cpu/pybind.cpython-312-x86_64-linux-gnu.so
xz -T2 -9 "$so"  # 216 MB -> 37 MB; gpu_check.sh unpacks it
(cd .dev/debs && apt-get download libx11-6 libx11-data libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 libgl1 libglx0 \
    libglvnd0 libudev1 libgomp1)
du -sh .dev
