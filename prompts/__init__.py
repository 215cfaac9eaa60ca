"""The LLM prompts of `segmo segment-texts`, shipped inside the package as `segmo._prompts`
(pyproject.toml maps this folder there; `segmo.text.llm` reads it with importlib.resources).
Edit the .md and .json files; this file only makes the folder a package."""
