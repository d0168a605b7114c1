"""Ground node (laptop): registration, the paper's association, the apple map. Must import and run without torch."""
