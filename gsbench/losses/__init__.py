"""Loss terms: `terms` (the registry of named, weighted, scheduled terms every method configures),
`ssim` and `normal_consistency` (the fused C++ kernels of two of them, ``csrc/``, with their PyTorch
references)."""
