"""Preprocessing stages (paper Fig. 1): bias correction, localisation, intensity, slice crop/centre."""
