"""Every line of Taichi in taichi-gs lives in this package; nothing outside imports taichi."""
