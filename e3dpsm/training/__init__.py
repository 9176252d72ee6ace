"""Training of E-3DPSM: the paper's losses (losses, projection), windows over prepared data
(data), the learning-rate schedule, torchrun support (distributed) and the loop (trainer).
Nothing is imported here so that the CLI can read `ablations` without loading torch."""
