#!/usr/bin/env bash
# A CPU Vulkan driver for testing the GPU kernels without a GPU: Mesa 25's lavapipe from Debian
# bookworm-backports, unpacked into .gl/ next to (never over) the system Mesa.
#
#   source scripts/vulkan.sh     # set up (once) and export VK_ICD_FILENAMES / LD_LIBRARY_PATH
#   bash scripts/vulkan.sh       # set up (once) and print the export lines
#
# Why not bookworm's own lavapipe (Mesa 22.3.6): it drops loop iterations that contain an atomic,
# which breaks the rasterizer's tile loops (tests/test_gpu_backend.py has a canary for this).
# Steps: apt-get install mesa-vulkan-drivers libvulkan1 (bookworm: the loader and the driver's
# shared-library dependencies such as libLLVM-15); a private apt source for bookworm-backports with
# the same URI as the machine's main Debian source; apt-get download mesa-vulkan-drivers, libdrm2,
# libdrm-amdgpu1 from it; dpkg -x into .gl/vulkan/root; an ICD JSON pointing at its lavapipe.
# Idempotent: a second run only exports. Debian/Ubuntu-style apt only; needs root (or sudo) the
# first time for the apt-get install.

_vk_main() {
    local repo root gl apt icd sudo uri lib
    repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
    gl="$repo/.gl/vulkan"
    root="$gl/root"
    apt="$gl/apt"
    icd="$gl/lvp_icd.json"
    lib="$root/usr/lib/x86_64-linux-gnu"
    command -v apt-get >/dev/null && command -v dpkg >/dev/null \
        || { echo "vulkan.sh: needs Debian's apt-get and dpkg (bookworm); install a Vulkan driver by hand" >&2; return 1; }
    if ! dpkg -s libvulkan1 mesa-vulkan-drivers >/dev/null 2>&1; then
        sudo=""
        [ "$(id -u)" = 0 ] || sudo="sudo"
        $sudo apt-get -o DPkg::Lock::Timeout=300 update -qq || return 1
        DEBIAN_FRONTEND=noninteractive $sudo apt-get -o DPkg::Lock::Timeout=300 install -y -qq \
            --no-install-recommends mesa-vulkan-drivers libvulkan1 >/dev/null || return 1
    fi
    if [ ! -f "$icd" ] || [ ! -f "$lib/libvulkan_lvp.so" ]; then
        # the main Debian archive URI of this machine (deb822 or one-line sources)
        uri="$(grep -rhoE '^URIs:[[:space:]]*[^ ]+/debian/?$' /etc/apt/sources.list.d/*.sources 2>/dev/null \
               | head -n1 | awk '{print $2}')"
        [ -n "$uri" ] || uri="$(grep -rhoE '^deb[[:space:]]+(\[[^]]*\][[:space:]]+)?[^ ]+/debian/?[[:space:]]' \
               /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null | head -n1 | awk '{print $NF}')"
        [ -n "$uri" ] || { echo "vulkan.sh: no Debian source found in /etc/apt; add one or set it up by hand" >&2; return 1; }
        rm -rf "$apt" && mkdir -p "$apt/parts" "$apt/lists/partial" "$apt/cache/archives/partial" "$apt/debs"
        printf 'Types: deb\nURIs: %s\nSuites: bookworm-backports\nComponents: main\nSigned-By: %s\n' \
            "$uri" /usr/share/keyrings/debian-archive-keyring.gpg >"$apt/parts/backports.sources"
        local opts=(-o "Dir::Etc::SourceList=/dev/null" -o "Dir::Etc::SourceParts=$apt/parts"
                    -o "Dir::State::Lists=$apt/lists" -o "Dir::Cache=$apt/cache" -o "Debug::NoLocking=1" -o "APT::Sandbox::User=root")
        apt-get "${opts[@]}" update -qq || return 1
        (cd "$apt/debs" && apt-get "${opts[@]}" download -qq \
            mesa-vulkan-drivers/bookworm-backports libdrm2/bookworm-backports libdrm-amdgpu1/bookworm-backports) \
            || return 1
        rm -rf "$root" && mkdir -p "$root"
        local deb
        for deb in "$apt"/debs/*.deb; do dpkg -x "$deb" "$root" || return 1; done
        [ -f "$lib/libvulkan_lvp.so" ] || { echo "vulkan.sh: no libvulkan_lvp.so in the backports package" >&2; return 1; }
        sed "s#\"library_path\": *\"[^\"]*\"#\"library_path\": \"$lib/libvulkan_lvp.so\"#" \
            "$root/usr/share/vulkan/icd.d/lvp_icd.json" >"$icd.tmp" && mv "$icd.tmp" "$icd"
    fi
    export VK_ICD_FILENAMES="$icd"
    case ":${LD_LIBRARY_PATH:-}:" in
        *":$lib:"*) ;;
        *) export LD_LIBRARY_PATH="$lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" ;;
    esac
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
    set -euo pipefail
    _vk_main
    echo "export VK_ICD_FILENAMES=$VK_ICD_FILENAMES"
    echo "export LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
else
    _vk_main
fi
