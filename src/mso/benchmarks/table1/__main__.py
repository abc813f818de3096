"""``python -m mso.benchmarks.table1``, as before the module became a package."""

from mso.benchmarks.table1 import main

raise SystemExit(main())
