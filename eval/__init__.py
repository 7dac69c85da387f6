"""Scoring of capssim results: metrics, Siemens-star MTF, benchmark runner and reports."""
