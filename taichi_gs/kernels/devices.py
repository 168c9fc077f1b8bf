"""What compute devices this machine has, asked of the drivers directly (ctypes, no Taichi init).

Taichi falls back to the CPU silently and does not report which GPU it took, so the runtime asks
here first: the CUDA driver for its device name, and the Vulkan loader for its physical devices
(name, type, the largest storage buffer it binds). A Vulkan device of type CPU (Mesa's lavapipe,
SwiftShader) is a software rasterizer: right for tests, never a speed-up, so ``auto`` skips it.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
from dataclasses import dataclass
from pathlib import Path

# VkPhysicalDeviceType
VK_TYPE_NAMES = {0: "other", 1: "integrated GPU", 2: "discrete GPU", 3: "virtual GPU", 4: "CPU (software)"}
VK_HARDWARE_TYPES = (1, 2, 3)
# Byte offsets in VkPhysicalDeviceProperties (x86-64 / arm64 layout): apiVersion 0, deviceType 16,
# deviceName[256] 20, limits at 296 (8-aligned after the 16-byte pipeline cache UUID);
# VkPhysicalDeviceLimits: maxStorageBufferRange +28, maxPerStageDescriptorStorageBuffers +76.
_OFF_TYPE, _OFF_NAME, _OFF_LIMITS = 16, 20, 296
_LIM_STORAGE_RANGE, _LIM_STORAGE_BUFFERS = 28, 76


@dataclass(frozen=True)
class VulkanDevice:
    """One Vulkan physical device as the loader reports it."""

    index: int
    name: str
    device_type: int
    api_minor: int
    max_storage_buffer_bytes: int
    max_storage_buffers_per_stage: int

    @property
    def software(self) -> bool:
        """True for a CPU implementation (lavapipe, SwiftShader)."""
        return self.device_type not in VK_HARDWARE_TYPES

    def describe(self) -> str:
        kind = VK_TYPE_NAMES.get(self.device_type, "unknown")
        return f"{self.name} [Vulkan 1.{self.api_minor} {kind}]"


class _InstanceCreateInfo(ctypes.Structure):
    _fields_ = [
        ("sType", ctypes.c_int), ("pNext", ctypes.c_void_p), ("flags", ctypes.c_uint32),
        ("pApplicationInfo", ctypes.c_void_p), ("enabledLayerCount", ctypes.c_uint32),
        ("ppEnabledLayerNames", ctypes.c_void_p), ("enabledExtensionCount", ctypes.c_uint32),
        ("ppEnabledExtensionNames", ctypes.c_void_p),
    ]


def vulkan_devices() -> list[VulkanDevice]:
    """Vulkan physical devices in the loader's order ([] without a loader or a driver)."""
    try:
        lib = ctypes.CDLL("libvulkan.so.1" if platform.system() != "Darwin" else "libvulkan.1.dylib")
    except OSError:
        return []
    lib.vkCreateInstance.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    lib.vkEnumeratePhysicalDevices.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint32), ctypes.c_void_p]
    lib.vkGetPhysicalDeviceProperties.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
    lib.vkDestroyInstance.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
    info = _InstanceCreateInfo(sType=1)  # VK_STRUCTURE_TYPE_INSTANCE_CREATE_INFO
    instance = ctypes.c_void_p()
    if lib.vkCreateInstance(ctypes.byref(info), None, ctypes.byref(instance)) != 0:
        return []
    try:
        count = ctypes.c_uint32(0)
        if lib.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), None) != 0 or count.value == 0:
            return []
        handles = (ctypes.c_void_p * count.value)()
        lib.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), handles)
        found = []
        for i, handle in enumerate(handles[: count.value]):
            buf = ctypes.create_string_buffer(4096)  # the struct is ~824 bytes
            lib.vkGetPhysicalDeviceProperties(handle, buf)
            raw = buf.raw
            api = struct.unpack_from("<I", raw, 0)[0]
            found.append(VulkanDevice(
                index=i,
                name=raw[_OFF_NAME:_OFF_NAME + 256].split(b"\0")[0].decode(errors="replace"),
                device_type=struct.unpack_from("<i", raw, _OFF_TYPE)[0],
                api_minor=(api >> 12) & 0x3FF,
                max_storage_buffer_bytes=struct.unpack_from("<I", raw, _OFF_LIMITS + _LIM_STORAGE_RANGE)[0],
                max_storage_buffers_per_stage=struct.unpack_from("<I", raw, _OFF_LIMITS + _LIM_STORAGE_BUFFERS)[0],
            ))
        return found
    finally:
        lib.vkDestroyInstance(instance, None)


def taichi_vulkan_pick(devices: list[VulkanDevice]) -> VulkanDevice | None:
    """The device Taichi 1.7's Vulkan backend takes: ``TI_VISIBLE_DEVICE`` if valid, else the best
    score (discrete 1000, integrated 500, plus 100 per API minor version; first one on a tie)."""
    if not devices:
        return None
    visible = os.environ.get("TI_VISIBLE_DEVICE", "")
    if visible.isdigit() and int(visible) < len(devices):
        return devices[int(visible)]

    def score(d: VulkanDevice) -> int:
        return {2: 1000, 1: 500}.get(d.device_type, 0) + 100 * d.api_minor

    best = devices[0]
    for d in devices[1:]:
        if score(d) > score(best):
            best = d
    return best


def cuda_device_name() -> str | None:
    """Name of CUDA device 0, or None without a usable NVIDIA driver and GPU."""
    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    count = ctypes.c_int(0)
    if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0 or count.value == 0:
        return None
    device = ctypes.c_int(0)
    name = ctypes.create_string_buffer(256)
    if lib.cuDeviceGet(ctypes.byref(device), 0) != 0 or lib.cuDeviceGetName(name, 256, device) != 0:
        return "CUDA device 0"
    return name.value.decode(errors="replace")


def cpu_model() -> str:
    """The CPU's model name."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown CPU"
