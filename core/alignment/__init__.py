"""Alignment: Procrustes/GPA and transformation synchronisation (CVPR 2015)."""
