"""capssim's benchmarks, one module per subject, all run as ``capssim bench SUBJECT``."""
