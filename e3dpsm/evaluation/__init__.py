"""Evaluation: benchmark figures from predictions (core, torch-free), running a torch model
over prepared data (runner), a checkpoint's results and report folder for `e3dpsm evaluate`
(evaluate), Markdown tables (tables) and plots (plots)."""
