"""The training configs, one YAML per stage and dataset, shipped inside the package as
`segmo._configs` (pyproject.toml maps this folder there; the demo reads it with
importlib.resources). Edit or copy the YAML files; this file only makes the folder a package."""
