"""Synthetic egocentric event data: a head-mounted fisheye sees an articulated body act out
the ten EE3D action classes in a textured room; events come from log-intensity changes.

Entry points: `generator.generate_sequence`, `dataset.write_dataset`, CLI `e3dpsm synth`.
"""
