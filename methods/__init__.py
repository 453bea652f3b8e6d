"""Method plugins (installed as ``gsbench.methods``): one module per method, registered lazily."""
