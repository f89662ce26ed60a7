"""The harness: package format, loader, safety checks and the runtime (critics, orchestrator,
recoveries) that the env worker, the critic service, the evolver and the tools all run."""
