from benchmarks._cli import main

main("pipeline")
