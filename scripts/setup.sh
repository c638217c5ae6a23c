#!/usr/bin/env bash
# Set up cdpr_dynamics on a fresh machine without ROS: a venv in .venv with the ROS 2 Jazzy
# wheels, the numerical dependencies and this package (editable), then run the main job: the
# live demo (dynamics_node + a scripted controller + the FRF service; PNG and MCAP in out/).
#   bash scripts/setup.sh            # install and run the demo
#   bash scripts/setup.sh --no-run   # install only (CI)
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
venv="$root/.venv"
python=${PYTHON:-python3}

if [ ! -x "$venv/bin/python" ]; then
  "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --upgrade pip
"$venv/bin/python" -m pip install --quiet -r "$root/requirements.txt"
"$venv/bin/python" -m pip install --quiet --no-deps --no-build-isolation -e "$root"

# pip -e does not install data_files: lay out share/ as an installed ament_python package has it.
share="$venv/share/cdpr_dynamics"
mkdir -p "$share" "$venv/share/ament_index/resource_index/packages"
ln -sfn "$root/package.xml" "$share/package.xml"
ln -sfn "$root/config" "$share/config"
ln -sfn "$root/launch" "$share/launch"
touch "$venv/share/ament_index/resource_index/packages/cdpr_dynamics"

# The wheels find their libraries and interfaces through the ament index of the venv.
if ! grep -q 'cdpr_dynamics environment' "$venv/bin/activate"; then
  cat >> "$venv/bin/activate" <<ACT
# cdpr_dynamics environment
export AMENT_PREFIX_PATH="$venv\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=\${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
ACT
fi
echo "cdpr_dynamics installed in $venv (activate with: source .venv/bin/activate)"

if [ "${1:-}" != "--no-run" ]; then
  # shellcheck disable=SC1091
  source "$venv/bin/activate"
  cdpr_demo --output out/cdpr_demo.png
fi
