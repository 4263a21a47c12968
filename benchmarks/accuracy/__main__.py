from benchmarks._cli import main

main("accuracy")
