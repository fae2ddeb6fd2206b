#!/bin/sh
# The one install step of CI (.ci/run) and of the Docker image (deploy/Dockerfile), so that what CI proves
# is what the image runs (tests/test_deploy_and_examples.py checks both call it the same way):
#   sh deploy/install-wheel.sh dist/gcdtrav-*.whl
# CPU torch first, otherwise pip resolves a multi-GB CUDA build; TORCH_INDEX_URL names the index that
# serves the CPU build where pip's default does not (the Dockerfile sets PyTorch's CPU index).
set -eu
wheel=$1
pip install --quiet ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} torch==2.13.0
pip install --quiet "${wheel}[service]"
