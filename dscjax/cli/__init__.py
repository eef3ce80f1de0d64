"""The `dscjax` command line: one module per subcommand, each with `HELP`, `add_options` and
`run`."""
