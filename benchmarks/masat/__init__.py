"""The MASAT paper's pose-graph protocol: comparison with the paper's rates (``compare_to_paper``),
the same runs in the real g2o (``g2o_parity``) and their statistics (``paper_stats``)."""
