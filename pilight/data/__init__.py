"""Data contracts: EXR I/O, the sample schema, shards, splits and relighting pairs."""
