"""The paper's three experiments (streaming, localization, baseline comparison), each a module
of runners that return plain result records; ``python -m bench`` runs them and writes the docs."""
