"""The repository around the package: docs/DESIGN.md, README.md, envs/, the developer set-up."""
