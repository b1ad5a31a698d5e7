"""One adapter per method the benchmark can score, all behind one protocol."""
