"""Files: image reading and writing (atomic writes, TIFF/PNG), output folders and the JSON schema checker."""
