#!/usr/bin/env bash
# Installs the test tools that come from outside PyPI into .tools/ (git-ignored):
# the Khronos glTF-Validator (npm package gltf-validator, pinned), which
# tests/test_gltf_validator.py runs on the smoke run's scene.glb through scripts/validate_gltf.js.
# Without node/npm it says so and installs nothing (that test then skips, naming the reason).
set -euo pipefail
cd "$(dirname "$0")/.."
prefix="${JAXDISTILL_TOOLS:-.tools}/node"
if ! command -v npm >/dev/null 2>&1 || ! command -v node >/dev/null 2>&1; then
    echo "install_test_tools: node/npm not found: the glTF-Validator test will be skipped" >&2
    exit 0
fi
if [ ! -f "$prefix/node_modules/gltf-validator/package.json" ]; then
    npm install --silent --no-audit --no-fund --prefix "$prefix" gltf-validator@2.0.0-dev.3.10
fi
