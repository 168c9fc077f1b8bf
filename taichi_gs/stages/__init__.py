"""The three stages of the method: pose (1), refine (2), deblur (3)."""
