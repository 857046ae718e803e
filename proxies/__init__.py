"""Neural proxies: per base mesh, a visibility and a depth net that predict where a ray
entering its box hits it, so shards can route rays without holding that geometry.

Render path (no torch): inference.Proxy, cache.ProxyCache, policy.plan_proxies.
Training (torch, the 'train' extra): train.train_proxy, `nprt proxy train`, nprt.proxies.ship;
across the cluster, one Ray task per mesh: tasks.RayTrainer.
"""
