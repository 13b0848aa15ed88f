#!/usr/bin/env bash
# The whole test suite, on a fresh machine: creates .venv, installs, runs pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
# headless Chromium for the report.html rendering test (apt-get as root; else that test skips)
bash scripts/install_test_browser.sh
# Keep DDS discovery on this machine, and tests out of other ROS graphs' way.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 101 ))}
export RMW_IMPLEMENTATION=${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}
# Test files or folders among the arguments replace the default `tests` (bash scripts/test.sh
# tests/bev_mapper_core/methods/ipm/test_ipm.py runs that file only); other arguments (-m "not slow", -k ...) go to pytest.
paths=()
for a in "$@"; do
  case "$a" in -*) ;; *) [ -e "${a%%::*}" ] && paths+=("$a") ;; esac
done
if [ ${#paths[@]} -eq 0 ]; then
  set -- tests "$@"
fi
exec .venv/bin/python -m pytest -q -p no:cacheprovider "$@"
