"""Evaluation: benchmark figures from predictions (core, torch-free), running a torch model
over prepared data (runner), Markdown tables (tables) and plots (plots)."""
