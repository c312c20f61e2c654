# The ROS 2 Jazzy oracle on rmw_cyclonedds_cpp (sourced by scripts/test.sh after setup_lib.sh).
# PyPI ships Jazzy with Fast DDS only, so tests/oracle/rmw-cyclonedds builds rmw_cyclonedds_cpp
# from source into a prefix whose rclpy runs on either RMW (RMW_IMPLEMENTATION per process).
#
# On success exports RCAN_RTPS_ORACLE_JAZZY_CYCLONE (the prefix's python). A prefix given in
# that variable is used as it is. A failed build is not fatal here: it exports
# RCAN_RTPS_ORACLE_JAZZY_CYCLONE_ERROR, the Cyclone tests skip with it, and under CI=true
# they fail instead (tests/conftest.py).

# What the prefix is built from: the recipe's script and sources, and the interpreter.
cyclone_stamp() {  # recipe-dir
  { (cd "$1" && sha256sum build_rmw_cyclonedds.sh rmw_cyclonedds-src.tar.gz); "$PY" -V; } \
    | sha256sum | cut -c1-16
}

ensure_cyclone_oracle() {  # prefix recipe-dir
  local prefix=$1 recipe=$2 stamp log
  if [ -n "${RCAN_RTPS_ORACLE_JAZZY_CYCLONE:-}" ]; then
    echo "using $RCAN_RTPS_ORACLE_JAZZY_CYCLONE"
    return 0
  fi
  stamp=$(cyclone_stamp "$recipe")
  if [ -f "$prefix/.stamp" ] && [ "$(cat "$prefix/.stamp")" = "$stamp" ]; then
    echo "cyclone oracle up to date"
  else
    log=$prefix.log
    rm -rf "$prefix"
    echo "building it (about 3 min; log: $log)"
    if PYTHON=$PY bash "$recipe/build_rmw_cyclonedds.sh" "$prefix" >"$log" 2>&1; then
      echo "$stamp" >"$prefix/.stamp"
      rm -rf "$prefix.build"
    else
      tail -n 20 "$log" >&2
      rm -rf "$prefix" "$prefix.build"  # nothing half-built is trusted by the next run
      export RCAN_RTPS_ORACLE_JAZZY_CYCLONE_ERROR="its build failed (log: $log)"
      echo "the cyclone oracle did not build; its tests will skip (and fail under CI=true)" >&2
      return 0
    fi
  fi
  RCAN_RTPS_ORACLE_JAZZY_CYCLONE="$(cd "$prefix" && pwd)/bin/python"
  export RCAN_RTPS_ORACLE_JAZZY_CYCLONE
}
