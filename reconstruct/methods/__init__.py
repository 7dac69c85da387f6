"""One module per reconstruction method; each registers itself with ``@register_method``."""
