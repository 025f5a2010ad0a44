"""Every artifact's schema and its read/write/validate functions (Parquet, EXR, PNG, PLY)."""
