"""Densification strategies (docs/design.md §3.3): the shared interface and parameter surgery (`base`),
3DGS's (`default`), GOF / RaDe-GS's abs-gradient one (`absgrad`) and IBGS's sparsity-aware one (`sparsity`)."""
