"""Maps datasets: a LeRobot dataset's frames explained into parquet shards on one machine or a Ray cluster, and
their views, videos, report, Rerun recording and faithfulness. The top room below the command line: nothing else
in the package imports it."""
