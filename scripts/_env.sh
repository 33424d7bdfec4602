# shellcheck shell=bash
# Shared bootstrap of the wip-ros scripts. Source it (do not execute it), then call
# `wip_bootstrap`:
#
#   source "$(dirname "${BASH_SOURCE[0]}")/_env.sh"
#   wip_bootstrap
#
# wip_bootstrap runs scripts/setup when the venv or the colcon workspace is missing or out of
# date (a check of a few stamp files, about 0.1 s when nothing changed), then activates them
# in the calling shell:
#   - the venv .venv (VIRTUAL_ENV, PATH),
#   - AMENT_PREFIX_PATH and CMAKE_PREFIX_PATH with the venv prefix (the ROS wheels install
#     their ament index and CMake configs there),
#   - ros_ws/install/setup.bash (sourced with `set +u`: colcon's scripts read unset variables),
#   - ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, ROS_DOMAIN_ID (1..101, from the shell's pid) and
#     RMW_IMPLEMENTATION=rmw_fastrtps_cpp and OPENBLAS_NUM_THREADS=1, each only when not
#     set already; the two ROS_ defaults set are listed in WIP_ROS_DEFAULTS (NAME=VALUE),
#     which hardware mode and check_base use to go back to the user's ROS environment.
# It also unsets _ROS_WHEELS_BOOTSTRAP_COMPLETE: the ros-wheels-bootstrapper .pth of a venv
# re-executes Python once with LD_LIBRARY_PATH set for *that* venv and marks the environment
# with this variable; a value inherited from a process of another venv would skip our venv's
# set-up (docs/ros-from-pip.md).
#
# Variables it defines: REPO_ROOT, WIP_VENV, WIP_WS (and exports WIP_REPO_ROOT).

if [ -z "${BASH_VERSION:-}" ]; then
    echo 'scripts/_env.sh: needs bash' >&2
    # shellcheck disable=SC2317  # reached when the file is executed instead of sourced
    return 1 2>/dev/null || exit 1
fi

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
WIP_VENV="${REPO_ROOT}/.venv"
WIP_WS="${REPO_ROOT}/ros_ws"
export WIP_REPO_ROOT="${REPO_ROOT}"

# Bump when the set-up procedure changes in a way that needs a reinstall or a rebuild.
WIP_SETUP_VERSION=1
# Arguments of `colcon build`; part of the build stamp. --symlink-install makes the ament_python
# packages "develop" installs of ros_ws/src, so that editing node code needs no rebuild.
WIP_COLCON_ARGS=(--symlink-install --cmake-args -DBUILD_TESTING=OFF)
# Standard ROS interface packages that ros_ws/src carries for a ROS installation that lacks
# them (the ROS 2 wheels on PyPI have no tf2_msgs); built only where the underlay has none
# (wip_colcon_skip_args), so that a Jazzy install's own package is used there.
WIP_STANDARD_INTERFACES=(tf2_msgs)
WIP_REQUIREMENTS_STAMP="${WIP_VENV}/.wip-requirements.sha256"
WIP_BUILD_STAMP="${WIP_WS}/install/.wip-build.sha256"

wip_log() {
    # Short progress line on stderr, e.g. "setup: building the workspace".
    printf '%s: %s\n' "${WIP_LOG_PREFIX:-wip}" "$*" >&2
}

wip_requirements_hash() {
    # Hash of the pip requirements files and of the set-up procedure version.
    {
        echo "setup-version ${WIP_SETUP_VERSION}"
        local f
        for f in "${REPO_ROOT}"/requirements*.txt; do
            [ -f "$f" ] || continue
            echo "== ${f##*/}"
            cat "$f"
        done
    } | sha256sum | cut -d' ' -f1
}

wip_build_hash() {
    # Hash of what a colcon build depends on: the requirements, the colcon arguments, the
    # location of the workspace (install trees hold absolute paths), the list of all source
    # files, and the content of every source file except Python modules (those are linked
    # into the install tree by --symlink-install, so editing them needs no rebuild).
    {
        echo "setup-version ${WIP_SETUP_VERSION}"
        echo "requirements $(wip_requirements_hash)"
        echo "colcon ${WIP_COLCON_ARGS[*]}"
        echo "root ${REPO_ROOT}"
        (
            cd "${WIP_WS}/src" &&
                find . \( -name __pycache__ -o -name '*.egg-info' -o -name .pytest_cache \) \
                    -prune -o -type f ! -name '*.pyc' -print | LC_ALL=C sort
        )
        (
            cd "${WIP_WS}/src" &&
                find . \( -name __pycache__ -o -name '*.egg-info' -o -name .pytest_cache \) \
                    -prune -o -type f ! -name '*.pyc' \( ! -name '*.py' -o -name setup.py \) \
                    -print0 | LC_ALL=C sort -z | xargs -0 -r sha256sum
        )
    } | sha256sum | cut -d' ' -f1
}

wip_colcon_skip_args() {
    # wip_colcon_skip_args PREFIX...: print `--packages-skip NAME...` (one word a line) for
    # the packages of WIP_STANDARD_INTERFACES that the ament index of one of the underlay
    # prefixes already holds; nothing when every one of them is to be built from ros_ws.
    local name prefix skip=()
    for name in "${WIP_STANDARD_INTERFACES[@]}"; do
        for prefix in "$@"; do
            if [ -e "${prefix}/share/ament_index/resource_index/packages/${name}" ]; then
                skip+=("${name}")
                break
            fi
        done
    done
    [ "${#skip[@]}" = 0 ] || printf '%s\n' --packages-skip "${skip[@]}"
}

wip_unfixed_cmake_exports() {
    # Print the message wheels' CMake export files that still name the wheel build machine's
    # paths (fix 3 of docs/ros-from-pip.md), if any.
    local files=("${WIP_VENV}"/share/*/cmake/*__rosidl_generator_pyExport.cmake)
    [ -e "${files[0]}" ] || return 0
    grep -l -F '/opt/python/' "${files[@]}" || true
}

wip_setup_needed() {
    # Succeeds (returns 0) when scripts/setup has work to do; prints the reason on stdout.
    if [ ! -x "${WIP_VENV}/bin/python" ]; then
        echo 'no venv'
    elif [ "$(cat "${WIP_REQUIREMENTS_STAMP}" 2>/dev/null)" != "$(wip_requirements_hash)" ]; then
        echo 'requirements changed'
    elif [ -n "$(wip_unfixed_cmake_exports)" ]; then
        echo 'CMake exports of the message wheels not fixed'
    elif [ ! -f "${WIP_WS}/install/setup.bash" ]; then
        echo 'workspace not built'
    elif [ "$(cat "${WIP_BUILD_STAMP}" 2>/dev/null)" != "$(wip_build_hash)" ]; then
        echo 'workspace sources changed'
    else
        return 1
    fi
}

_wip_path_prepend() {
    # _wip_path_prepend VAR DIR: put DIR first in the colon-separated list VAR (once).
    local name="$1" dir="$2" out='' part parts=()
    IFS=':' read -r -a parts <<<"${!1:-}"
    for part in "${parts[@]}"; do
        [ -n "${part}" ] && [ "${part}" != "${dir}" ] && out="${out:+${out}:}${part}"
    done
    export "${name}=${dir}${out:+:${out}}"
}

_wip_strip_foreign_ros_libs() {
    # Drop from LD_LIBRARY_PATH the library folders of ROS wheels of *other* venvs, which a
    # parent process of another venv may have put there.
    local out='' part parts=()
    IFS=':' read -r -a parts <<<"${LD_LIBRARY_PATH:-}"
    for part in "${parts[@]}"; do
        case "${part}" in
            "${WIP_VENV}"/*) ;;
            */site-packages/ros_*.libs) continue ;;
        esac
        [ -n "${part}" ] && out="${out:+${out}:}${part}"
    done
    if [ -n "${out}" ]; then export LD_LIBRARY_PATH="${out}"; else unset LD_LIBRARY_PATH; fi
}

wip_activate_venv() {
    # Activate the venv and the ROS prefix inside it (no workspace). Used for the build too.
    unset PYTHONHOME _ROS_WHEELS_BOOTSTRAP_COMPLETE
    export VIRTUAL_ENV="${WIP_VENV}"
    _wip_path_prepend PATH "${WIP_VENV}/bin"
    _wip_path_prepend AMENT_PREFIX_PATH "${WIP_VENV}"
    _wip_path_prepend CMAKE_PREFIX_PATH "${WIP_VENV}"
    _wip_strip_foreign_ros_libs
    hash -r
}

wip_activate() {
    # Activate the venv and the built workspace, and keep DDS traffic on this host.
    if [ ! -f "${WIP_WS}/install/setup.bash" ]; then
        wip_log "no ${WIP_WS}/install/setup.bash: run scripts/setup first"
        return 1
    fi
    wip_activate_venv
    local restore_u=0
    case $- in *u*) restore_u=1 ;; esac
    set +u
    # shellcheck disable=SC1091  # generated by colcon
    source "${WIP_WS}/install/setup.bash"
    local status=$?
    [ "${restore_u}" = 1 ] && set -u
    if [ "${status}" != 0 ]; then
        wip_log "sourcing ${WIP_WS}/install/setup.bash failed (${status})"
        return "${status}"
    fi
    # The venv must stay first in AMENT_PREFIX_PATH's underlays and on PATH.
    _wip_path_prepend PATH "${WIP_VENV}/bin"
    case ":${AMENT_PREFIX_PATH}:" in
        *":${WIP_VENV}:"*) ;;
        *) export AMENT_PREFIX_PATH="${AMENT_PREFIX_PATH}:${WIP_VENV}" ;;
    esac
    # Defaults for simulations: localhost only, and a domain of our own per run, so that
    # parallel runs on this host do not see each other (the launcher replaces this pid-derived
    # id by one reserved on the host: wip_bringup.private_domain). 1..101: Fast DDS ports of higher
    # domain ids run into Linux's ephemeral port range. Each default set is recorded in
    # WIP_ROS_DEFAULTS: hardware mode and check_base drop it again, because a robot's base
    # is on the user's domain and network (ROS's defaults: domain 0, SUBNET).
    local defaulted=''
    if [ -z "${ROS_AUTOMATIC_DISCOVERY_RANGE:-}" ]; then
        export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
        defaulted="${defaulted} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST"
    fi
    if [ -z "${ROS_DOMAIN_ID:-}" ]; then
        export ROS_DOMAIN_ID="$(($$ % 101 + 1))"
        defaulted="${defaulted} ROS_DOMAIN_ID=${ROS_DOMAIN_ID}"
    fi
    if [ -n "${defaulted}" ]; then
        export WIP_ROS_DEFAULTS="${WIP_ROS_DEFAULTS:+${WIP_ROS_DEFAULTS} }${defaulted# }"
    fi
    export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
    # One BLAS thread: the control math uses small matrices, for which OpenBLAS's thread
    # pool only adds wake-ups (measured: the in-process runner 10-20 % less CPU).
    export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
    hash -r
}

wip_bootstrap() {
    # Set up (only if needed) and activate the environment; see the top of this file.
    local reason
    if reason="$(wip_setup_needed)"; then
        wip_log "setting up (${reason})"
        "${REPO_ROOT}/scripts/setup" || return $?
    fi
    wip_activate
}
