"""Polarization maths: Stokes vectors from the four analyzer angles and back, DoLP/AoP, physical validity."""
