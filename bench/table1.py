from mso.benchmarks.table1 import main  # Table 1 of the paper; --help for the options

raise SystemExit(main())
