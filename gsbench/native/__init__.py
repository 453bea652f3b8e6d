"""Native code: `build` (the one loader that compiles and loads every C++/OpenMP library of the project)
and `impl_choice` (which implementation of a kernel runs: the fast path or its PyTorch reference)."""
