"""Neural proxies: per base mesh, a visibility and a depth net that predict where a ray
entering its box hits it, so shards can route rays without holding that geometry.

Render path (no torch): inference.Proxy, cache.ProxyCache, policy.plan_proxies; the
accuracy target (accuracy: bands from each proxy's held-out error curve, the predicted
error) and its exact check after a render (check).
Training (torch, the 'train' extra): train.train_proxy, `nprt proxy train`, nprt.proxies.ship;
across the cluster, one Ray task per mesh: tasks.RayTrainer.
"""
