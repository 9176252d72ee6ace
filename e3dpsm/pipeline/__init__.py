"""The main job: synth -> prepare -> train -> evaluate -> export -> parity -> quantize ->
validate -> golden -> clip -> profile -> report, on the embedded default (synthetic data,
small model).

- `stages`:  the one stage table (each stage's name, done-marker, CLI command and reports);
- `runner`:  runs the table, one `python -m e3dpsm` subprocess per stage, resumable;
- `report`:  OUT/report/index.md, .html and pipeline.json, read from the stage table;
- `compare`: two runs' reports compared for regressions (`e3dpsm compare`), torch-free.

Modules are imported by name (no re-exports here), so that `compare` stays light to import.
"""
