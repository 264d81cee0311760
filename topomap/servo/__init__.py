"""Appearance servoing: relative pose from two images, control laws, disturbance observer (THESIS.md section 3)."""
