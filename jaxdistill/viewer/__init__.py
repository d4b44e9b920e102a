"""The browser viewer of a run's out_dir (`jaxdistill view OUT_DIR`, `python -m jaxdistill.view`).

display.py: images, glTF and camera poses as arrays (no viser); run.py: reading a finished or
running out_dir; app.py: the viser scene and controls. Needs the `view` extra (viser).
"""
