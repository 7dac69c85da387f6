"""Runtime services: memory checks and the allocator, worker threads, out-of-range data warnings."""
