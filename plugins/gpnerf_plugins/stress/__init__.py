"""Built-in stress cases: source views and baseline, pose noise, image corruption, textureless and unseen scenes."""
