from setuptools import find_packages, setup

package_name = 'pisc_bench'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_bench']),
        ('share/pisc_bench', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description="PISC benchmarks and the soak: the plant's work-precision, the batch, the lockstep graph, the parser, bags, identification, commissioning, and minutes of real time under load.",
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_integrators = pisc_bench.integrators_cli:main',
            'pisc_batch_bench = pisc_bench.batch_bench_cli:main',
            'pisc_commission_bench = pisc_bench.commission_bench_cli:main',
            'pisc_soak = pisc_bench.soak_cli:main',
            'pisc_bench = pisc_bench.bench_cli:main',
            'pisc_parser_bench = pisc_bench.parser_bench_cli:main',
        ],
    },
)
