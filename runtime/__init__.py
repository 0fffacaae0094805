"""The ground floor every stage and command stands on: the stage contract (`runtime.stage`:
StageSpec, StageContext, Loaded), a stage's code version from its import closure
(`runtime.code_closure`) and the console (`runtime.console`: progress lines, the shared rich
console). It imports only runfs and schemas (docs/architecture.md, "Floors")."""
