"""Pipeline stages: one module per stage, each with Settings, inputs(), outputs(), run()."""
