#!/usr/bin/env bash
# Side-by-side fusion + tracking benchmark on the same TUM frames and parameters:
# patch_mapper's bench_fusion (Rust, rayon) and Open3D's CPU tensor SLAM pipeline (PyPI open3d-cpu).
# Both run with 2 threads. Usage: launch_scripts/bench_fusion_vs_open3d.sh [dataset_dir] [passes]
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/.." && pwd)"
dataset="${1:-$root/tests/data/tum_fr1_xyz}"
passes="${2:-2}"
venv="$root/.venv-open3d"

if ! ldconfig -p | grep -q "libusb-1.0.so.0"; then
    # Open3D's import needs Debian's libusb-1.0-0.
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get install -y -q libusb-1.0-0 >/dev/null || { apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null; }
    else
        echo "Open3D's import needs Debian's libusb-1.0-0: sudo apt-get install -y libusb-1.0-0" >&2
        exit 1
    fi
fi
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
"$venv/bin/python" -c "import open3d" 2>/dev/null || "$venv/bin/pip" install -q open3d-cpu

export RAYON_NUM_THREADS=2 OMP_NUM_THREADS=2
echo "=== patch_mapper (Rust) ==="
cargo build --release -q -p patch_mapper --bin bench_fusion --manifest-path "$root/Cargo.toml"
"$root/target/release/bench_fusion" "$dataset" "$passes"
echo
echo "=== Open3D (CPU tensor pipeline) ==="
"$venv/bin/python" "$here/bench_fusion_vs_open3d.py" "$dataset" --passes "$passes" --threads 2
