# Environment for every process the project starts: sourced by scripts/run and scripts/test.
# The venv prefix is the ament prefix of the ROS 2 Jazzy wheels.
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
# DDS discovery stays on this machine unless the user exported a setting of their own.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export PATH="$VENV/bin:$PATH"
