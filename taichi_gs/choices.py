"""The names of the command line's closed choices, each written once: the modules that act on a name check it
against its tuple here, and ``cli.py`` builds its enums from them. Pure tuples, importing nothing, so that
``taichi-gs --help`` starts without NumPy, OpenCV or Taichi (the stages' names stay with their declarations in
``stages/declaration.py``: STAGE_NAMES)."""

# Taichi backends (kernels/runtime.py): auto takes CUDA, then Metal or a hardware Vulkan GPU, then the CPU.
ARCH_CHOICES = ("auto", "cpu", "cuda", "vulkan", "metal")

# The presets every stage declares (its PRESETS' keys; a test checks they agree): ours, then the paper's method.
PRESET_NAMES = ("fast", "paper")

# synth.py: camera motions and blur levels; synth_scenes.py: room kinds.
TRAJECTORIES = ("translation", "turn", "handheld")
BLUR_LEVELS = ("none", "moderate", "extreme")
SCENES = ("room", "office", "plain", "corridor")

# export.py's render_path: the camera paths (camera_paths.py).
RENDER_PATHS = ("orbit", "trajectory")

# export.py's writers, then mesh.py's TSDF mesh.
EXPORT_FORMATS = ("nerfstudio", "colmap", "ply", "3dgs", "mesh")
