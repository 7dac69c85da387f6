"""The scene library: one module per scene, each describing geometry, materials, depth and purpose."""
