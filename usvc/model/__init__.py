"""ACE-style scene coordinate regression network: frozen encoder (`encoder`, `xfeat_encoder`),
per-scene head and map files (`head`), image preprocessing (`preprocess`), options (`options`)."""
