from mso.benchmarks.lifetime import main  # the energy study; --help for the options

raise SystemExit(main())
