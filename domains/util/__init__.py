"""Infrastructure shared by the whole library, not worlds or data: float64 inside npbrs
(:mod:`.precision`), objects that enter compiled programs as arguments (:mod:`.pytree`), the
compile options of npbrs's programs (:mod:`.compiling`), small dense linear algebra in plain XLA
operations (:mod:`.linalg`) and atomic file writes (:mod:`.files`)."""
