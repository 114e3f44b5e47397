"""What every process needs below the model: atomic files, devices, torch.distributed, signals, run folders and
profiling stages."""
