"""mutmut's test command: pytest in this process, exit 1 on any failure.

mutmut 2.x counts only exit status 1 as a killed mutant, so a mutant that breaks the import
(pytest's exit 2, an error at collection) would read as survived. In-process (no wrapper
shell), so mutmut's timeout stops the tests themselves: a shell's orphaned pytest would hold
mutmut's pipe open and the run would wait forever. docs/testing.md, "Mutation testing".

    mutmut run --paths-to-mutate e3dpsm/budget.py \
        --runner "python tests/_mutmut_runner.py -x -q -p no:cacheprovider --noconftest tests/test_budget.py"
"""
import sys

import pytest

if __name__ == "__main__":
    sys.exit(1 if pytest.main(sys.argv[1:]) else 0)
